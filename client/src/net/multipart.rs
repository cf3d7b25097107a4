//! Decoding range responses: `Content-Range` headers and `multipart/byteranges` bodies
//! (RFC 9110 §14.4 and §14.6).
//!
//! The parser trusts nothing: a part's length comes from its own `Content-Range`, every offset is
//! checked against the body, and a part whose range disagrees with the resource length or runs
//! past the body is an error. It never panics and allocates nothing per part beyond the returned
//! slices (which share the body's buffer).

use bytes::Bytes;

/// One decoded part: the absolute byte range it carries and its bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RangePart {
    /// First byte (absolute).
    pub start: u64,
    /// One past the last byte.
    pub end: u64,
    /// Total length of the resource, when the server stated it (`*` otherwise).
    pub complete_len: Option<u64>,
    /// The part's bytes (`end − start` of them).
    pub body: Bytes,
}

/// Why a range response could not be decoded.
#[derive(Debug, Clone, thiserror::Error, PartialEq, Eq)]
pub enum MultipartError {
    /// `Content-Range` is not `bytes A-B/LEN` with `A ≤ B < LEN`.
    #[error("bad Content-Range {0:?}")]
    ContentRange(String),
    /// `Content-Type` has no usable boundary.
    #[error("multipart response without a boundary")]
    NoBoundary,
    /// The body does not follow the multipart syntax.
    #[error("malformed multipart body: {0}")]
    Syntax(&'static str),
    /// A part runs past the end of the body.
    #[error("multipart part {start}-{end} runs past the body ({body_len} bytes)")]
    Truncated {
        /// Part start.
        start: u64,
        /// Part end (exclusive).
        end: u64,
        /// Body length.
        body_len: usize,
    },
}

/// Parses a `Content-Range: bytes A-B/LEN` (or `/*`) value into `(A, B + 1, LEN)`.
pub fn parse_content_range(v: &str) -> Result<(u64, u64, Option<u64>), MultipartError> {
    let bad = || MultipartError::ContentRange(v.chars().take(100).collect());
    let rest = v.trim();
    let (unit, rest) = rest.split_once(' ').ok_or_else(bad)?;
    if !unit.eq_ignore_ascii_case("bytes") {
        return Err(bad());
    }
    let (span, len) = rest.trim().split_once('/').ok_or_else(bad)?;
    let (a, b) = span.split_once('-').ok_or_else(bad)?;
    let num = |s: &str| -> Result<u64, MultipartError> {
        if s.is_empty() || !s.bytes().all(|c| c.is_ascii_digit()) {
            return Err(bad());
        }
        s.parse::<u64>().map_err(|_| bad())
    };
    let (a, b) = (num(a)?, num(b)?);
    let len = if len == "*" { None } else { Some(num(len)?) };
    if a > b || len.is_some_and(|l| b >= l) {
        return Err(bad());
    }
    Ok((a, b + 1, len))
}

/// The boundary parameter of a `multipart/byteranges` content type, or `None` when the type is
/// something else.
pub fn multipart_boundary(content_type: &str) -> Option<Result<String, MultipartError>> {
    let mut params = content_type.split(';');
    let mime = params.next()?.trim();
    if !mime.eq_ignore_ascii_case("multipart/byteranges") {
        return None;
    }
    for p in params {
        if let Some((k, v)) = p.trim().split_once('=')
            && k.trim().eq_ignore_ascii_case("boundary")
        {
            let v = v.trim().trim_matches('"');
            if v.is_empty() || v.len() > 70 {
                return Some(Err(MultipartError::NoBoundary));
            }
            return Some(Ok(v.to_string()));
        }
    }
    Some(Err(MultipartError::NoBoundary))
}

fn find(hay: &[u8], needle: &[u8], from: usize) -> Option<usize> {
    if needle.is_empty() || from > hay.len() {
        return None;
    }
    hay[from..]
        .windows(needle.len())
        .position(|w| w == needle)
        .map(|p| p + from)
}

/// Decodes a `multipart/byteranges` body. Parts come back in body order.
pub fn parse_multipart(body: &Bytes, boundary: &str) -> Result<Vec<RangePart>, MultipartError> {
    let delim = format!("--{boundary}");
    let delim = delim.as_bytes();
    let mut parts = Vec::new();
    // The first delimiter may be preceded by a preamble (normally a CRLF or nothing).
    let mut pos = find(body, delim, 0).ok_or(MultipartError::Syntax("no opening delimiter"))? + delim.len();
    loop {
        let rest = &body[pos.min(body.len())..];
        if rest.starts_with(b"--") {
            return Ok(parts); // closing delimiter; an epilogue may follow
        }
        if !rest.starts_with(b"\r\n") {
            return Err(MultipartError::Syntax("delimiter not followed by CRLF"));
        }
        pos += 2;
        let head_end = find(body, b"\r\n\r\n", pos).ok_or(MultipartError::Syntax("part headers do not end"))?;
        let head =
            std::str::from_utf8(&body[pos..head_end]).map_err(|_| MultipartError::Syntax("non-UTF-8 part header"))?;
        let mut range = None;
        for line in head.split("\r\n") {
            if let Some((k, v)) = line.split_once(':')
                && k.trim().eq_ignore_ascii_case("content-range")
            {
                range = Some(parse_content_range(v)?);
            }
        }
        let (start, end, complete_len) = range.ok_or(MultipartError::Syntax("part without Content-Range"))?;
        let data = head_end + 4;
        let len = usize::try_from(end - start).map_err(|_| MultipartError::Syntax("part too large"))?;
        let data_end = data
            .checked_add(len)
            .filter(|&e| e <= body.len())
            .ok_or(MultipartError::Truncated {
                start,
                end,
                body_len: body.len(),
            })?;
        parts.push(RangePart {
            start,
            end,
            complete_len,
            body: body.slice(data..data_end),
        });
        // After the data: CRLF, then the next delimiter.
        let after = &body[data_end..];
        if !after.starts_with(b"\r\n") || !after[2..].starts_with(delim) {
            return Err(MultipartError::Syntax("part data not followed by a delimiter"));
        }
        pos = data_end + 2 + delim.len();
    }
}

/// Cuts each wanted range out of the parts that came back. A server may coalesce neighbouring
/// ranges into one part, so each wanted range is looked up in whichever part contains it.
/// Returns `None` for a wanted range no part covers.
pub fn slice_wanted(parts: &[RangePart], wanted: &[std::ops::Range<u64>]) -> Vec<Option<Bytes>> {
    wanted
        .iter()
        .map(|w| {
            parts.iter().find(|p| p.start <= w.start && w.end <= p.end).map(|p| {
                let a = (w.start - p.start) as usize;
                let b = (w.end - p.start) as usize;
                p.body.slice(a..b)
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn body(boundary: &str, parts: &[(u64, &[u8])], total: u64) -> Bytes {
        let mut b = Vec::new();
        for (start, data) in parts {
            b.extend_from_slice(format!("\r\n--{boundary}\r\n").as_bytes());
            b.extend_from_slice(b"Content-Type: application/octet-stream\r\n");
            let end = start + data.len() as u64 - 1;
            b.extend_from_slice(format!("Content-Range: bytes {start}-{end}/{total}\r\n\r\n").as_bytes());
            b.extend_from_slice(data);
        }
        b.extend_from_slice(format!("\r\n--{boundary}--\r\n").as_bytes());
        Bytes::from(b)
    }

    #[test]
    fn content_range_cases() {
        assert_eq!(parse_content_range("bytes 0-0/1"), Ok((0, 1, Some(1))));
        assert_eq!(parse_content_range("BYTES 5-9/*"), Ok((5, 10, None)));
        for bad in [
            "bytes 5-4/10",
            "bytes 0-10/10",
            "items 0-1/2",
            "bytes -1/2",
            "bytes 0-1",
            "bytes a-b/c",
            "",
        ] {
            assert!(parse_content_range(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn boundary_from_content_type() {
        assert_eq!(
            multipart_boundary("multipart/byteranges; boundary=abc123"),
            Some(Ok("abc123".into()))
        );
        assert_eq!(
            multipart_boundary("Multipart/ByteRanges; charset=x; boundary=\"q\""),
            Some(Ok("q".into()))
        );
        assert_eq!(multipart_boundary("application/octet-stream"), None);
        assert_eq!(
            multipart_boundary("multipart/byteranges"),
            Some(Err(MultipartError::NoBoundary))
        );
    }

    #[test]
    fn parts_decode_and_binary_data_may_contain_the_boundary() {
        // The data itself contains "--B": lengths come from Content-Range, not from scanning.
        let b = body("B", &[(0, b"ab--B\r\nxx"), (100, b"z")], 200);
        let parts = parse_multipart(&b, "B").expect("parses");
        assert_eq!(parts.len(), 2);
        assert_eq!(&parts[0].body[..], b"ab--B\r\nxx");
        assert_eq!((parts[1].start, parts[1].end), (100, 101));
        let got = slice_wanted(&parts, &[2..5, 100..101, 50..60]);
        assert_eq!(got[0].as_deref(), Some(&b"--B"[..]));
        assert_eq!(got[1].as_deref(), Some(&b"z"[..]));
        assert_eq!(got[2], None);
    }

    #[test]
    fn truncated_and_malformed_bodies_are_errors() {
        let b = body("B", &[(0, b"0123456789")], 20);
        for cut in 0..b.len() - 1 {
            // Any cut before the closing delimiter's end is an error, never a panic.
            let r = parse_multipart(&b.slice(..cut), "B");
            if cut < b.len() - 4 {
                assert!(r.is_err(), "cut at {cut} parsed");
            }
        }
        assert!(parse_multipart(&Bytes::from_static(b"garbage"), "B").is_err());
        let lying = Bytes::from_static(b"--B\r\nContent-Range: bytes 0-99/100\r\n\r\nshort\r\n--B--");
        assert!(matches!(
            parse_multipart(&lying, "B"),
            Err(MultipartError::Truncated { .. })
        ));
    }

    proptest! {
        #[test]
        fn never_panics_on_arbitrary_bodies(data in proptest::collection::vec(any::<u8>(), 0..400)) {
            let _ = parse_multipart(&Bytes::from(data), "B");
        }

        #[test]
        fn round_trip(lens in proptest::collection::vec(1usize..50, 1..8)) {
            let mut parts = Vec::new();
            let mut off = 0u64;
            let datas: Vec<Vec<u8>> = lens.iter().enumerate().map(|(i, &n)| vec![i as u8; n]).collect();
            for d in &datas {
                parts.push((off, d.as_slice()));
                off += d.len() as u64 + 7;
            }
            let b = body("xyz", &parts, off + 1);
            let got = parse_multipart(&b, "xyz").expect("parses");
            prop_assert_eq!(got.len(), datas.len());
            for (g, d) in got.iter().zip(&datas) {
                prop_assert_eq!(&g.body[..], &d[..]);
            }
        }
    }
}
