//! Heightmap import: a 16-bit grayscale PNG (decoded by the `image` crate's PNG decoder) or a
//! single-band GeoTIFF (the `tiff` crate) becomes a [`Heightfield`].
//!
//! Conventions: image column → +x, image row → +z (row 0 at the grid's min z; a north-up map has
//! north at −z); one sample per pixel. A PNG's 0..=65535 maps linearly onto the caller's height
//! range `MIN:MAX` metres; a GeoTIFF's u16, i16 or f32 samples are metres (a u16 one may be mapped
//! like a PNG's instead). The cell size is the caller's, else a GeoTIFF's ModelPixelScaleTag
//! (33550); the origin (sample (0, 0)) is the caller's, else a GeoTIFF's ModelTiepointTag (33922:
//! raster `(I, J)` at model `(X, Y)`, north-up, so x = X − I·sx and z = −(Y + J·sy)), else the
//! grid centred on (0, 0). No-data samples (NaN, ±∞, or a GeoTIFF's GDAL_NODATA value) are filled
//! with the lowest valid height.
//!
//! Hostile input: sizes are checked against the shared limits before anything is allocated for
//! the samples, the decoders run with memory limits, and every failure is an [`ImportError`]
//! whose message names what was found.

use std::io::Cursor;

use canopy_shared::terrain::{Heightfield, MAX_SAMPLES, MAX_SIDE_SAMPLES, TerrainError};
use image::ImageDecoder;
use image::codecs::png::PngDecoder;

/// A heightmap's container.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum HeightmapFormat {
    /// PNG.
    Png,
    /// TIFF (GeoTIFF).
    Tiff,
}

impl HeightmapFormat {
    /// The format its first bytes say (PNG signature, TIFF or BigTIFF header).
    pub fn detect(bytes: &[u8]) -> Option<Self> {
        if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
            Some(Self::Png)
        } else if [&b"II*\0"[..], b"MM\0*", b"II+\0", b"MM\0+"]
            .iter()
            .any(|m| bytes.starts_with(m))
        {
            Some(Self::Tiff)
        } else {
            None
        }
    }
}

/// What the caller says about a heightmap.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ImportOptions {
    /// Sample spacing, metres (required unless a GeoTIFF gives its pixel scale).
    pub cell: Option<f64>,
    /// Metres of the 16-bit values 0 and 65535 (required for a PNG).
    pub heights: Option<[f32; 2]>,
    /// Position of sample (0, 0): x, z.
    pub origin: Option<[f64; 2]>,
    /// The samples the heightmap must have along x and z.
    pub samples: Option<[u32; 2]>,
}

impl ImportOptions {
    /// Sets one option from its text (`cell`: metres; `heights`: `MIN:MAX`; `origin`: `X,Z`;
    /// `samples`: `NX,NZ`), as the CLI and the API's query parameters give it; false for a name
    /// that is none of these.
    pub fn set(&mut self, name: &str, value: &str) -> Result<bool, String> {
        let num = |s: &str, what: &str| -> Result<f64, String> {
            s.trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| format!("{what} {value:?}: not a finite number"))
        };
        let pair = |sep: char, what: &str| -> Result<(f64, f64), String> {
            let (a, b) = value
                .split_once(sep)
                .ok_or_else(|| format!("{what} {value:?}: expected two numbers separated by {sep:?}"))?;
            Ok((num(a, what)?, num(b, what)?))
        };
        match name {
            "cell" => self.cell = Some(num(value, "cell")?),
            "heights" => {
                let (lo, hi) = pair(':', "heights")?;
                self.heights = Some([lo as f32, hi as f32]);
            }
            "origin" => {
                let (x, z) = pair(',', "origin")?;
                self.origin = Some([x, z]);
            }
            "samples" => {
                let (nx, nz) = pair(',', "samples")?;
                let count = |v: f64| {
                    (v.fract() == 0.0 && (0.0..=f64::from(u32::MAX)).contains(&v))
                        .then_some(v as u32)
                        .ok_or_else(|| format!("samples {value:?}: expected two whole numbers"))
                };
                self.samples = Some([count(nx)?, count(nz)?]);
            }
            _ => return Ok(false),
        }
        Ok(true)
    }
}

/// An imported heightmap.
#[derive(Debug, Clone, PartialEq)]
pub struct Imported {
    /// The heightfield.
    pub field: Heightfield,
    /// Its container.
    pub format: HeightmapFormat,
    /// Its sample type (`u16`, `i16`, `f32`).
    pub sample: &'static str,
    /// No-data samples filled with the lowest valid height.
    pub filled: u64,
}

/// Why a heightmap is refused.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// Neither PNG nor TIFF.
    #[error("not a heightmap: expected a PNG or a TIFF file (its first bytes are neither)")]
    Unknown,
    /// The PNG decoder failed (truncated, corrupt).
    #[error("PNG: {0}")]
    Png(String),
    /// The TIFF decoder failed (truncated, corrupt, unsupported compression).
    #[error("TIFF: {0}")]
    Tiff(String),
    /// A bit depth, colour type, band count or sample format other than a heightmap's.
    #[error("{0}")]
    Depth(String),
    /// Too small, past the limits, or not the size asked for.
    #[error("{0}")]
    Size(String),
    /// An option missing or out of range.
    #[error("{0}")]
    Options(String),
    /// The heightfield refused (cell, origin, heights).
    #[error(transparent)]
    Terrain(#[from] TerrainError),
}

/// Imports a PNG or TIFF heightmap (told apart by its first bytes).
pub fn import(bytes: &[u8], opts: &ImportOptions) -> Result<Imported, ImportError> {
    match HeightmapFormat::detect(bytes) {
        Some(HeightmapFormat::Png) => import_png(bytes, opts),
        Some(HeightmapFormat::Tiff) => import_tiff(bytes, opts),
        None => Err(ImportError::Unknown),
    }
}

/// Checks a declared size, before its samples are allocated.
fn check_size(nx: u32, nz: u32, opts: &ImportOptions) -> Result<(), ImportError> {
    if nx < 2 || nz < 2 {
        return Err(ImportError::Size(format!(
            "the heightmap is {nx} × {nz} samples: at least 2 × 2"
        )));
    }
    if nx > MAX_SIDE_SAMPLES || nz > MAX_SIDE_SAMPLES || u64::from(nx) * u64::from(nz) > MAX_SAMPLES {
        return Err(ImportError::Size(format!(
            "the heightmap is {nx} × {nz} samples: at most {MAX_SIDE_SAMPLES} a side and {MAX_SAMPLES} in all"
        )));
    }
    if let Some([ex, ez]) = opts.samples
        && [ex, ez] != [nx, nz]
    {
        return Err(ImportError::Size(format!(
            "the heightmap is {nx} × {nz} samples, expected {ex} × {ez}"
        )));
    }
    Ok(())
}

fn check_range(h: [f32; 2]) -> Result<(f32, f32), ImportError> {
    let [lo, hi] = h;
    if lo.is_finite() && hi.is_finite() && hi > lo && lo.abs() <= 1e5 && hi.abs() <= 1e5 {
        Ok((lo, hi))
    } else {
        Err(ImportError::Options(format!(
            "heights {lo}:{hi}: need finite MIN < MAX within ±100000 m"
        )))
    }
}

/// Metres of 16-bit values mapped onto `[lo, hi]`.
fn map_u16(v: &[u16], range: [f32; 2]) -> Result<Vec<f32>, ImportError> {
    let (lo, hi) = check_range(range)?;
    let step = f64::from(hi - lo) / 65_535.0;
    Ok(v.iter()
        .map(|&q| (f64::from(lo) + f64::from(q) * step) as f32)
        .collect())
}

/// The cell size: the caller's, else the file's, else an error.
fn cell_of(opts: &ImportOptions, from_file: Option<f64>, what: &str) -> Result<f64, ImportError> {
    let cell = opts.cell.or(from_file).ok_or_else(|| {
        ImportError::Options(format!(
            "{what} gives no sample spacing: give the cell size in metres (--cell M, or cell=M)"
        ))
    })?;
    if cell.is_finite() && cell > 0.0 {
        Ok(cell)
    } else {
        Err(ImportError::Options(format!(
            "cell size {cell}: need a positive number of metres"
        )))
    }
}

/// Centres the grid on (0, 0).
fn centred(cell: f64, nx: u32, nz: u32) -> [f64; 2] {
    [-cell * f64::from(nx - 1) / 2.0, -cell * f64::from(nz - 1) / 2.0]
}

/// Fills no-data samples (`None`) with the lowest valid height; returns the heights and how many
/// were filled.
fn fill(samples: Vec<Option<f32>>) -> Result<(Vec<f32>, u64), ImportError> {
    let lo = samples.iter().flatten().copied().fold(f32::INFINITY, f32::min);
    if !lo.is_finite() {
        return Err(ImportError::Size(
            "every sample of the heightmap is no-data (NaN or the no-data value)".into(),
        ));
    }
    let filled = samples.iter().filter(|s| s.is_none()).count() as u64;
    Ok((samples.into_iter().map(|s| s.unwrap_or(lo)).collect(), filled))
}

/// Imports a 16-bit grayscale PNG: needs the cell size and the height range.
pub fn import_png(bytes: &[u8], opts: &ImportOptions) -> Result<Imported, ImportError> {
    let png = |e: image::ImageError| ImportError::Png(e.to_string());
    // The size from the header (IHDR comes first), checked before the decoder reads on.
    if bytes.len() >= 24 && &bytes[12..16] == b"IHDR" {
        let be = |o: usize| u32::from_be_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
        check_size(be(16), be(20), opts)?;
    }
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(2 * MAX_SAMPLES + (16 << 20));
    let decoder = PngDecoder::with_limits(Cursor::new(bytes), limits).map_err(png)?;
    let (nx, nz) = decoder.dimensions();
    let found = decoder.original_color_type();
    if found != image::ExtendedColorType::L16 {
        return Err(ImportError::Depth(format!(
            "the PNG is {}: a heightmap must be 16-bit grayscale (one 16-bit channel, no alpha)",
            describe_png(found)
        )));
    }
    check_size(nx, nz, opts)?;
    let range = opts.heights.ok_or_else(|| {
        ImportError::Options(
            "a PNG heightmap needs its height range: the metres of 0 and 65535 (--heights MIN:MAX, or heights=MIN:MAX)"
                .into(),
        )
    })?;
    let cell = cell_of(opts, None, "a PNG")?;
    let mut buf = vec![0u8; 2 * nx as usize * nz as usize];
    if decoder.total_bytes() != buf.len() as u64 {
        return Err(ImportError::Png(format!(
            "{} bytes of samples for {nx} × {nz} 16-bit pixels",
            decoder.total_bytes()
        )));
    }
    decoder.read_image(&mut buf).map_err(png)?;
    let q: Vec<u16> = buf.chunks_exact(2).map(|c| u16::from_ne_bytes([c[0], c[1]])).collect();
    let heights = map_u16(&q, range)?;
    let origin = opts.origin.unwrap_or_else(|| centred(cell, nx, nz));
    Ok(Imported {
        field: Heightfield::new(origin, cell, [nx, nz], &heights)?,
        format: HeightmapFormat::Png,
        sample: "u16",
        filled: 0,
    })
}

fn describe_png(c: image::ExtendedColorType) -> String {
    use image::ExtendedColorType as C;
    let bits = c.bits_per_pixel() / u16::from(c.channel_count().max(1));
    let kind = match c {
        C::L1 | C::L2 | C::L4 | C::L8 | C::L16 => "grayscale",
        C::La1 | C::La2 | C::La4 | C::La8 | C::La16 => "grayscale with alpha",
        C::Rgb1 | C::Rgb2 | C::Rgb4 | C::Rgb8 | C::Rgb16 => "RGB colour",
        C::Rgba1 | C::Rgba2 | C::Rgba4 | C::Rgba8 | C::Rgba16 => "RGBA colour",
        C::Unknown(_) => "palette colour",
        _ => "colour",
    };
    if matches!(c, C::Unknown(_)) {
        format!("{kind} ({c:?})")
    } else {
        format!("{bits}-bit {kind}")
    }
}

/// The samples of a single-band TIFF, by type.
enum TiffSamples {
    U16(Vec<u16>),
    I16(Vec<i16>),
    F32(Vec<f32>),
}

/// Imports a single-band GeoTIFF of u16, i16 or f32 samples.
pub fn import_tiff(bytes: &[u8], opts: &ImportOptions) -> Result<Imported, ImportError> {
    use tiff::decoder::{Decoder, DecodingResult, Limits, ifd::Value};
    use tiff::tags::Tag;
    let tiff = |e: tiff::TiffError| ImportError::Tiff(e.to_string());
    let mut limits = Limits::default();
    limits.decoding_buffer_size = 4 * MAX_SAMPLES as usize + (1 << 20);
    limits.intermediate_buffer_size = 4 * MAX_SAMPLES as usize + (1 << 20);
    let mut d = Decoder::new(Cursor::new(bytes)).map_err(tiff)?.with_limits(limits);
    let (nx, nz) = d.dimensions().map_err(tiff)?;
    match d.colortype().map_err(tiff)? {
        tiff::ColorType::Gray(16 | 32) => {}
        tiff::ColorType::Gray(b) => {
            return Err(ImportError::Depth(format!(
                "the TIFF has {b}-bit samples: a heightmap needs u16, i16 or f32 samples"
            )));
        }
        tiff::ColorType::Multiband { num_samples, .. } => {
            return Err(ImportError::Depth(format!(
                "the TIFF has {num_samples} bands: a heightmap needs a single band"
            )));
        }
        tiff::ColorType::Palette(b) => {
            return Err(ImportError::Depth(format!(
                "the TIFF is {b}-bit palette colour: a heightmap needs a single band of heights"
            )));
        }
        other => {
            use tiff::ColorType as C;
            let bands = match other {
                C::GrayA(_) => 2,
                C::RGBA(_) | C::CMYK(_) => 4,
                C::CMYKA(_) => 5,
                _ => 3,
            };
            return Err(ImportError::Depth(format!(
                "the TIFF has {bands} bands ({other:?}): a heightmap needs a single band"
            )));
        }
    }
    check_size(nx, nz, opts)?;
    let f64s = |d: &mut Decoder<Cursor<&[u8]>>, tag: Tag| -> Result<Option<Vec<f64>>, ImportError> {
        match d.find_tag(tag).map_err(tiff)? {
            None => Ok(None),
            Some(v) => v.into_f64_vec().map(Some).map_err(tiff),
        }
    };
    let scale = f64s(&mut d, Tag::ModelPixelScaleTag)?;
    let tie = f64s(&mut d, Tag::ModelTiepointTag)?;
    let nodata: Option<f64> = match d.find_tag(Tag::GdalNodata).map_err(tiff)? {
        Some(Value::Ascii(s)) => {
            let s = s.trim_end_matches('\0').trim();
            Some(
                s.parse()
                    .map_err(|_| ImportError::Tiff(format!("GDAL_NODATA {s:?} is not a number")))?,
            )
        }
        _ => None,
    };
    let file_cell = match scale.as_deref() {
        Some([sx, sz, ..]) if opts.cell.is_none() => {
            if !(sx.is_finite() && sz.is_finite() && *sx > 0.0 && *sz > 0.0) {
                return Err(ImportError::Tiff(format!("ModelPixelScaleTag {sx} × {sz}")));
            }
            if (sx - sz).abs() > 1e-6 * sx.max(*sz) {
                return Err(ImportError::Options(format!(
                    "the GeoTIFF's pixels are {sx} × {sz}, not square: give --cell M to use one spacing"
                )));
            }
            if *sx < 0.01 {
                return Err(ImportError::Options(format!(
                    "the GeoTIFF's pixel scale {sx} looks like degrees (a geographic CRS): give --cell in metres"
                )));
            }
            Some(*sx)
        }
        _ => None,
    };
    let cell = cell_of(opts, file_cell, "the TIFF")?;
    let origin = match (opts.origin, tie.as_deref()) {
        (Some(o), _) => o,
        (None, Some([i, j, _, x, y, ..])) => [x - i * cell, -(y + j * cell)],
        (None, _) => centred(cell, nx, nz),
    };
    let samples = match d.read_image().map_err(tiff)? {
        DecodingResult::U16(v) => TiffSamples::U16(v),
        DecodingResult::I16(v) => TiffSamples::I16(v),
        DecodingResult::F32(v) => TiffSamples::F32(v),
        other => {
            let kind = match other {
                DecodingResult::U8(_) => "u8",
                DecodingResult::U32(_) => "u32",
                DecodingResult::U64(_) => "u64",
                DecodingResult::F16(_) => "f16",
                DecodingResult::F64(_) => "f64",
                DecodingResult::I8(_) => "i8",
                DecodingResult::I32(_) => "i32",
                _ => "i64",
            };
            return Err(ImportError::Depth(format!(
                "the TIFF has {kind} samples: a heightmap needs u16, i16 or f32 samples"
            )));
        }
    };
    let n = nx as usize * nz as usize;
    let valid = |v: f64| v.is_finite() && nodata.is_none_or(|nd| v != nd);
    let (raw, sample): (Vec<Option<f32>>, _) = match samples {
        TiffSamples::U16(v) if v.len() == n => match opts.heights {
            Some(range) => {
                let metres = map_u16(&v, range)?;
                let kept = v.iter().zip(metres).map(|(&q, h)| valid(f64::from(q)).then_some(h));
                (kept.collect(), "u16")
            }
            None => (
                v.iter().map(|&q| valid(f64::from(q)).then_some(f32::from(q))).collect(),
                "u16",
            ),
        },
        TiffSamples::I16(v) if v.len() == n => (
            v.iter().map(|&q| valid(f64::from(q)).then_some(f32::from(q))).collect(),
            "i16",
        ),
        TiffSamples::F32(v) if v.len() == n => (v.iter().map(|&h| valid(f64::from(h)).then_some(h)).collect(), "f32"),
        TiffSamples::U16(_) | TiffSamples::I16(_) | TiffSamples::F32(_) => {
            return Err(ImportError::Tiff(format!("the samples do not fill {nx} × {nz} pixels")));
        }
    };
    if opts.heights.is_some() && sample != "u16" {
        return Err(ImportError::Options(format!(
            "a height range (--heights) maps 16-bit unsigned samples; this TIFF's are {sample} metres already"
        )));
    }
    let (heights, filled) = fill(raw)?;
    Ok(Imported {
        field: Heightfield::new(origin, cell, [nx, nz], &heights)?,
        format: HeightmapFormat::Tiff,
        sample,
        filled,
    })
}

#[cfg(test)]
#[path = "import_tests.rs"]
mod tests;
