//! The glTF container: GLB chunks or plain JSON, the buffers the document refers to (the GLB BIN
//! chunk, base64 data URIs, files next to the model), and the asset version check.
//!
//! Buffers that cannot be loaded are kept as errors and only fail the import when an accessor
//! reads them. External files are read only from inside the model's folder.

use std::borrow::Cow;
use std::path::{Component, Path};

use gltf::json;

use super::{ImportError, Importer};

impl Importer<'_, '_> {
    /// Refuses glTF 1.0 and compressed meshes (Draco, meshopt); warns about other required
    /// extensions it ignores.
    pub(super) fn check_asset(&mut self) -> Result<(), ImportError> {
        let version = &self.root.asset.version;
        if !version.starts_with('2') {
            return Err(ImportError::Unsupported(format!("glTF version {version}")));
        }
        for ext in &self.root.extensions_required {
            match ext.as_str() {
                "KHR_draco_mesh_compression" | "EXT_meshopt_compression" => {
                    return Err(ImportError::Unsupported(format!("required extension {ext}")));
                }
                "KHR_mesh_quantization" | "KHR_texture_transform" | "KHR_materials_unlit" => {}
                _ => self.warnings.push(format!("required extension {ext} ignored")),
            }
        }
        Ok(())
    }
}

/// Splits the input into the JSON bytes and the GLB BIN chunk (if any).
pub(super) fn split_container(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>), ImportError> {
    if bytes.starts_with(b"glTF") {
        return split_glb(bytes);
    }
    let first = bytes
        .iter()
        .copied()
        .find(|b| !b.is_ascii_whitespace() && *b != 0xEF && *b != 0xBB && *b != 0xBF);
    match first {
        Some(b'{') => Ok((bytes, None)),
        Some(_) => Err(ImportError::NotGltf("neither GLB magic nor a JSON object".into())),
        None => Err(ImportError::NotGltf("empty input".into())),
    }
}

fn read_u32(bytes: &[u8], at: usize) -> Option<u32> {
    let b = bytes.get(at..at.checked_add(4)?)?;
    Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

fn split_glb(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>), ImportError> {
    let (Some(version), Some(declared)) = (read_u32(bytes, 4), read_u32(bytes, 8)) else {
        return Err(ImportError::TruncatedGlb(format!(
            "{} bytes, header needs 12",
            bytes.len()
        )));
    };
    if version != 2 {
        return Err(ImportError::MalformedGlb(format!("GLB version {version}, expected 2")));
    }
    let declared = declared as usize;
    if declared > bytes.len() {
        return Err(ImportError::TruncatedGlb(format!(
            "header declares {declared} bytes, only {} present",
            bytes.len()
        )));
    }
    if declared < 20 {
        return Err(ImportError::MalformedGlb(format!(
            "declared length {declared} leaves no room for a JSON chunk"
        )));
    }
    let data = &bytes[..declared];
    let mut at = 12usize;
    let mut json_chunk: Option<&[u8]> = None;
    let mut bin_chunk: Option<&[u8]> = None;
    while at < data.len() {
        let (Some(len), Some(kind)) = (read_u32(data, at), read_u32(data, at + 4)) else {
            return Err(ImportError::TruncatedGlb(format!(
                "chunk header at byte {at} is cut off"
            )));
        };
        let start = at + 8;
        let end = start
            .checked_add(len as usize)
            .filter(|&e| e <= data.len())
            .ok_or_else(|| {
                ImportError::TruncatedGlb(format!(
                    "chunk at byte {at} declares {len} bytes, only {} left",
                    data.len() - start
                ))
            })?;
        let body = &data[start..end];
        match &kind.to_le_bytes() {
            b"JSON" if json_chunk.is_none() && at == 12 => json_chunk = Some(body),
            b"JSON" => {
                return Err(ImportError::MalformedGlb("JSON chunk is not the first chunk".into()));
            }
            b"BIN\0" if json_chunk.is_some() && bin_chunk.is_none() => bin_chunk = Some(body),
            b"BIN\0" => {
                return Err(ImportError::MalformedGlb("unexpected BIN chunk".into()));
            }
            _ if json_chunk.is_none() => {
                return Err(ImportError::MalformedGlb("first chunk is not JSON".into()));
            }
            _ => {} // Unknown chunks are ignored, as the spec says.
        }
        // Chunks are 4-byte aligned; tolerate writers that did not pad the last chunk.
        at = end.checked_add(3).map_or(usize::MAX, |e| e & !3);
    }
    let json_chunk = json_chunk.ok_or_else(|| ImportError::MalformedGlb("no JSON chunk".into()))?;
    Ok((json_chunk, bin_chunk))
}

/// Loads every buffer of the document; a buffer that cannot be loaded is kept as its error.
pub(super) fn load_buffers<'a>(
    root: &json::Root,
    bin: Option<&'a [u8]>,
    base_dir: Option<&Path>,
) -> Vec<Result<Cow<'a, [u8]>, String>> {
    root.buffers
        .iter()
        .enumerate()
        .map(|(i, buffer)| {
            let data: Cow<'a, [u8]> = match &buffer.uri {
                None => match bin {
                    Some(b) if i == 0 => Cow::Borrowed(b),
                    Some(_) => return Err("only buffer 0 may use the GLB BIN chunk".into()),
                    None => return Err("no uri and no GLB BIN chunk".into()),
                },
                Some(uri) if uri.starts_with("data:") => Cow::Owned(decode_data_uri(uri)?),
                Some(uri) => Cow::Owned(read_external(uri, base_dir)?),
            };
            let want = usize::try_from(buffer.byte_length.0).unwrap_or(usize::MAX);
            if data.len() < want {
                return Err(format!(
                    "byteLength is {want} but only {} bytes are present",
                    data.len()
                ));
            }
            // Views must lie within byteLength; cut padding off.
            Ok(match data {
                Cow::Borrowed(b) => Cow::Borrowed(&b[..want]),
                Cow::Owned(mut v) => {
                    v.truncate(want);
                    Cow::Owned(v)
                }
            })
        })
        .collect()
}

/// Decodes a `data:[<mime>];base64,<payload>` URI.
fn decode_data_uri(uri: &str) -> Result<Vec<u8>, String> {
    let Some((head, payload)) = uri.split_once(',') else {
        return Err("data URI without a comma".into());
    };
    if !head.ends_with(";base64") {
        return Err("only base64 data URIs are supported".into());
    }
    base64_decode(payload)
}

/// Standard base64 (RFC 4648 alphabet, URL-safe characters also accepted), padding optional,
/// ASCII whitespace ignored.
pub fn base64_decode(text: &str) -> Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(text.len() / 4 * 3);
    let mut acc = 0u32;
    let mut bits = 0u32;
    let mut padding = false;
    for (pos, c) in text.bytes().enumerate() {
        let v = match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' | b'-' => 62,
            b'/' | b'_' => 63,
            b'=' => {
                padding = true;
                continue;
            }
            c if c.is_ascii_whitespace() => continue,
            _ => return Err(format!("invalid base64 character at {pos}")),
        };
        if padding {
            return Err(format!("base64 data after padding at {pos}"));
        }
        acc = (acc << 6) | u32::from(v);
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    if bits >= 6 {
        return Err("base64 data ends mid-byte".into());
    }
    Ok(out)
}

/// Reads an external buffer relative to `base_dir`. Absolute paths, URI schemes and `..`
/// components are refused so that a file cannot make the importer read outside its folder.
fn read_external(uri: &str, base_dir: Option<&Path>) -> Result<Vec<u8>, String> {
    let Some(base) = base_dir else {
        return Err(format!("external buffer {uri:?} but no base folder was given"));
    };
    if uri.contains("://") || uri.contains(':') {
        return Err(format!("unsupported URI {uri:?}"));
    }
    let decoded = percent_decode(uri);
    let rel = Path::new(&decoded);
    if rel
        .components()
        .any(|c| !matches!(c, Component::Normal(_) | Component::CurDir))
    {
        return Err(format!("refusing URI {uri:?} outside the model folder"));
    }
    let path = base.join(rel);
    std::fs::read(&path).map_err(|e| format!("cannot read {}: {e}", path.display()))
}

/// Decodes `%XX` escapes in a URI (invalid escapes are kept as they are).
pub(super) fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' && i + 2 < b.len() {
            let hex = std::str::from_utf8(&b[i + 1..i + 3])
                .ok()
                .and_then(|h| u8::from_str_radix(h, 16).ok());
            if let Some(v) = hex {
                out.push(v);
                i += 3;
                continue;
            }
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn base64_round_trip() {
        assert_eq!(base64_decode("aGVsbG8=").unwrap(), b"hello");
        assert_eq!(base64_decode("aGVsbG8").unwrap(), b"hello");
        assert_eq!(base64_decode("AAEC\n/w==").unwrap(), &[0, 1, 2, 255]);
        assert!(base64_decode("a$==").is_err());
        assert!(base64_decode("a").is_err());
    }

    #[test]
    fn glb_header_checks() {
        assert!(matches!(split_container(b"glTF"), Err(ImportError::TruncatedGlb(_))));
        let mut v = b"glTF".to_vec();
        v.extend_from_slice(&2u32.to_le_bytes());
        v.extend_from_slice(&4u32.to_le_bytes());
        assert!(matches!(split_container(&v), Err(ImportError::MalformedGlb(_))));
        assert!(matches!(split_container(b"\x00\x01"), Err(ImportError::NotGltf(_))));
    }

    #[test]
    fn percent_decoding() {
        assert_eq!(percent_decode("a%20b.bin"), "a b.bin");
        assert_eq!(percent_decode("a%2"), "a%2");
        assert_eq!(percent_decode("%"), "%");
    }
}
