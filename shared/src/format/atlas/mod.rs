//! Billboard atlases (section kind 7): multi-view images of the whole tree, one encoded image
//! per frame and resolution, located by a small table at the start of the section so that a
//! client fetches the table, then one frame by byte range, and checks that frame alone with its
//! own CRC-32. The byte layout is in `docs/format.md`, "Billboard atlases (kind 7)".
//!
//! View directions point from the tree to the camera, Y up. Azimuth θ and elevation σ (seed 001,
//! converted from its Z-up frame to Y-up) give `d = (cos σ cos θ, sin σ, −cos σ sin θ)`: θ = 0
//! looks from +X, θ = 90° from −Z, counter-clockwise seen from above.
//!
//! Every frame is an orthographic, square image of the bounding sphere stored in the table
//! (the sphere touches the image sides), camera up hint +Y (or +Z within 0.1° of ±Y), RGBA with
//! straight alpha on a transparent background.

use glam::Vec3;

use super::bytes::{Cursor, Writer};
use super::{FormatError, check_crc, crc32};

mod grid;
mod views;

pub use grid::{
    direction_angles, hemi_oct_blend, hemi_oct_decode, hemi_oct_direction, hemi_oct_encode, lat_long_direction,
    lat_long_nearest,
};
pub use views::{ViewBlend, ViewLocation, ViewSphere};

/// Largest number of resolutions per frame.
pub const MAX_ATLAS_RESOLUTIONS: usize = 4;
/// Largest number of layouts in one section.
pub const MAX_ATLAS_LAYOUTS: usize = 8;
/// Largest image side, pixels.
pub const MAX_ATLAS_RESOLUTION: u16 = 4096;
/// Largest number of frames in one section.
pub const MAX_ATLAS_FRAMES: u32 = 1 << 16;
/// Bytes of the fixed section header.
pub const ATLAS_HEADER_LEN: usize = 28;
/// Bytes of one layout record.
pub const ATLAS_LAYOUT_LEN: usize = 24;
/// Bytes of a frame record before its per-resolution entries.
pub const ATLAS_FRAME_FIXED_LEN: usize = 8;
/// Bytes of one per-resolution image entry (offset, length, CRC).
pub const ATLAS_IMAGE_ENTRY_LEN: usize = 12;
/// Bytes of one view direction of a views layout (azimuth, elevation: two `f32`).
pub const ATLAS_VIEW_ANGLES_LEN: usize = 8;
/// Default side of the hemi-octahedral grid.
pub const DEFAULT_HEMI_OCT_SIDE: u16 = 16;

/// Image codec of every frame in the section.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AtlasCodec {
    /// PNG, RGBA8.
    Png,
    /// WebP (lossless), RGBA8. Reserved: this bake writes PNG.
    Webp,
}

impl AtlasCodec {
    fn code(self) -> u8 {
        match self {
            Self::Png => 0,
            Self::Webp => 1,
        }
    }
    fn from_code(c: u8) -> Option<Self> {
        match c {
            0 => Some(Self::Png),
            1 => Some(Self::Webp),
            _ => None,
        }
    }
}

/// How a layout's frames are placed on the sphere of view directions.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum AtlasLayoutKind {
    /// Seed 001's latitude–longitude grid: frame `row · cols + col` looks from azimuth
    /// `col · azimuth_step` and elevation `elevation_min + row · elevation_step` (radians).
    LatLong {
        /// Elevation of row 0, radians.
        elevation_min: f32,
        /// Elevation step between rows, radians (≥ 0).
        elevation_step: f32,
        /// Azimuth step between columns, radians (> 0).
        azimuth_step: f32,
    },
    /// Hemi-octahedral grid of `side × side` frames over the upper hemisphere (Brucks'
    /// imposters): see [`hemi_oct_direction`] and [`hemi_oct_blend`].
    HemiOctahedral,
    /// Seed 000's two crossed quads: frame 0 seen from θ = 0 (+X), frame 1 from θ = 90° (−Z),
    /// both horizontal.
    CrossedQuads,
    /// Seed 001's irregular views (photographs): `cols` frames, each from its own direction,
    /// stored in the table ([`AtlasTable::view_angles`]); looked up by spherical Delaunay
    /// triangulation ([`ViewSphere`]). At most one such layout per section.
    Views,
}

impl AtlasLayoutKind {
    fn code(&self) -> u8 {
        match self {
            Self::LatLong { .. } => 0,
            Self::HemiOctahedral => 1,
            Self::CrossedQuads => 2,
            Self::Views => 3,
        }
    }

    /// Lower-case name (`lat_long`, `hemi_oct`, `crossed`, `views`).
    pub fn name(&self) -> &'static str {
        match self {
            Self::LatLong { .. } => "lat_long",
            Self::HemiOctahedral => "hemi_oct",
            Self::CrossedQuads => "crossed",
            Self::Views => "views",
        }
    }
}

/// One layout: a grid of `cols × rows` frames, frames `first_frame .. first_frame + cols·rows`
/// of the section's frame table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AtlasLayout {
    /// Placement of the frames.
    pub kind: AtlasLayoutKind,
    /// Columns (lat-long: azimuths; hemi-oct: side; crossed: 2; views: frames).
    pub cols: u16,
    /// Rows (lat-long: elevations; hemi-oct: side; crossed: 1; views: 1).
    pub rows: u16,
    /// Index of the layout's first frame in the frame table.
    pub first_frame: u32,
}

impl AtlasLayout {
    /// Frames in the layout.
    pub fn frame_count(&self) -> u32 {
        u32::from(self.cols) * u32::from(self.rows)
    }

    /// View direction (unit, tree → camera) of the layout's `local` frame, `None` if out of range
    /// or a [`AtlasLayoutKind::Views`] layout (its directions are in the table:
    /// [`AtlasTable::frame_direction`]).
    pub fn direction(&self, local: u32) -> Option<Vec3> {
        if local >= self.frame_count() {
            return None;
        }
        let cols = u32::from(self.cols);
        let (col, row) = (local % cols, local / cols);
        Some(match self.kind {
            AtlasLayoutKind::LatLong {
                elevation_min,
                elevation_step,
                azimuth_step,
            } => lat_long_direction(col as f32 * azimuth_step, elevation_min + row as f32 * elevation_step),
            AtlasLayoutKind::HemiOctahedral => hemi_oct_direction(col, row, u32::from(self.cols)),
            AtlasLayoutKind::CrossedQuads => lat_long_direction(col as f32 * std::f32::consts::FRAC_PI_2, 0.0),
            AtlasLayoutKind::Views => return None,
        })
    }
}

/// Where one encoded image lies: byte range relative to the section start, and its CRC-32.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ImageEntry {
    /// Offset from the section start.
    pub offset: u32,
    /// Length in bytes (0: absent).
    pub length: u32,
    /// CRC-32 of the image bytes.
    pub crc: u32,
}

/// One frame of the table: the root anchor and one image per resolution.
#[derive(Debug, Clone, PartialEq)]
pub struct AtlasFrame {
    /// Root (tree base, the origin) in the image: horizontal position from the left edge, as a
    /// fraction of the image width.
    pub root_u: f32,
    /// Root's distance from the image bottom as a fraction of the image height (seed 001's
    /// d1 / d2).
    pub root_v: f32,
    /// One entry per resolution of the section; all absent for an empty frame.
    pub images: Vec<ImageEntry>,
}

impl AtlasFrame {
    /// Whether the frame has images (an empty view stores none).
    pub fn is_present(&self) -> bool {
        self.images.iter().any(|e| e.length > 0)
    }
}

/// The section's table: everything but the images.
#[derive(Debug, Clone, PartialEq)]
pub struct AtlasTable {
    /// Codec of every image.
    pub codec: AtlasCodec,
    /// Framing sphere centre (tree space, metres).
    pub center: Vec3,
    /// Framing sphere radius: every frame's image spans `2·radius` metres a side.
    pub radius: f32,
    /// Image sides in pixels, one per resolution, strictly decreasing.
    pub resolutions: Vec<u16>,
    /// Layouts, in order; their frames tile the frame table.
    pub layouts: Vec<AtlasLayout>,
    /// Frame table.
    pub frames: Vec<AtlasFrame>,
    /// Azimuth and elevation (radians) of each frame of the views layout, in frame order;
    /// empty without one.
    pub view_angles: Vec<[f32; 2]>,
    /// The views layout's triangulation, built once at decode (shared: clients copy it into
    /// per-frame state); `None` without one.
    pub views: Option<std::sync::Arc<ViewSphere>>,
}

impl AtlasTable {
    /// Bytes of the table (header, layouts, view directions, frames, table CRC): a client's
    /// first fetch. `view_frames`: frames of the views layout (0 without one).
    pub fn table_len(resolutions: usize, layouts: usize, view_frames: usize, frames: usize) -> usize {
        ATLAS_HEADER_LEN
            + 2 * resolutions
            + ATLAS_LAYOUT_LEN * layouts
            + ATLAS_VIEW_ANGLES_LEN * view_frames
            + (ATLAS_FRAME_FIXED_LEN + ATLAS_IMAGE_ENTRY_LEN * resolutions) * frames
            + 4
    }

    /// Reads the table length from the first 4 bytes of the section.
    pub fn peek_table_len(prefix: &[u8]) -> Result<u32, FormatError> {
        Cursor::new(prefix, "atlas header").u32()
    }

    /// Decodes and validates the table from the section's first bytes (`prefix` must hold at
    /// least the table; more is ignored). `section_len` is the section length from the
    /// directory: every image range must lie inside it, and images must tile
    /// `[table_len, section_len)` in table order (frame-major, then resolution) with no gaps.
    pub fn decode(prefix: &[u8], section_len: u64) -> Result<Self, FormatError> {
        let table_len = Self::peek_table_len(prefix)? as usize;
        if table_len > prefix.len() {
            return Err(FormatError::Truncated {
                what: "atlas table",
                need: table_len as u64,
                have: prefix.len() as u64,
            });
        }
        if (table_len as u64) > section_len || table_len < ATLAS_HEADER_LEN + 4 {
            return Err(FormatError::invalid(
                "atlas table length",
                format!("{table_len} for a {section_len}-byte section"),
            ));
        }
        let body = &prefix[..table_len - 4];
        let stored = Cursor::new(&prefix[table_len - 4..table_len], "atlas table").u32()?;
        check_crc("atlas table", body, stored)?;
        let mut c = Cursor::new(body, "atlas table");
        c.u32()?;
        let codec =
            AtlasCodec::from_code(c.u8()?).ok_or_else(|| FormatError::invalid("atlas codec", "unknown code"))?;
        let nres = c.u8()? as usize;
        let nlay = c.u8()? as usize;
        c.u8()?;
        let frame_count = c.u32()?;
        let center = Vec3::new(
            c.finite_f32("atlas centre")?,
            c.finite_f32("atlas centre")?,
            c.finite_f32("atlas centre")?,
        );
        let radius = c.finite_f32("atlas radius")?;
        if radius <= 0.0 {
            return Err(FormatError::invalid("atlas radius", "not positive"));
        }
        if !(1..=MAX_ATLAS_RESOLUTIONS).contains(&nres) || nlay > MAX_ATLAS_LAYOUTS {
            return Err(FormatError::invalid(
                "atlas counts",
                format!("{nres} resolutions, {nlay} layouts"),
            ));
        }
        if frame_count > MAX_ATLAS_FRAMES {
            return Err(FormatError::invalid("atlas table length", "disagrees with the counts"));
        }
        let mut resolutions = Vec::with_capacity(nres);
        for _ in 0..nres {
            let r = c.u16()?;
            if r == 0 || r > MAX_ATLAS_RESOLUTION || resolutions.last().is_some_and(|&l| r >= l) {
                return Err(FormatError::invalid(
                    "atlas resolutions",
                    "not in 1..=4096 and strictly decreasing",
                ));
            }
            resolutions.push(r);
        }
        let mut layouts = Vec::with_capacity(nlay);
        let mut next_frame = 0u32;
        for _ in 0..nlay {
            let code = c.u8()?;
            c.u8()?;
            let cols = c.u16()?;
            let rows = c.u16()?;
            c.u16()?;
            let p = [
                c.finite_f32("atlas layout parameter")?,
                c.finite_f32("atlas layout parameter")?,
                c.finite_f32("atlas layout parameter")?,
            ];
            let first_frame = c.u32()?;
            let kind = match code {
                0 => AtlasLayoutKind::LatLong {
                    elevation_min: p[0],
                    elevation_step: p[1],
                    azimuth_step: p[2],
                },
                1 => AtlasLayoutKind::HemiOctahedral,
                2 => AtlasLayoutKind::CrossedQuads,
                3 => AtlasLayoutKind::Views,
                _ => return Err(FormatError::invalid("atlas layout kind", format!("{code}"))),
            };
            let shape_ok = match kind {
                AtlasLayoutKind::LatLong { .. } => cols >= 1 && rows >= 1,
                AtlasLayoutKind::HemiOctahedral => cols >= 1 && cols == rows,
                AtlasLayoutKind::CrossedQuads => cols == 2 && rows == 1,
                AtlasLayoutKind::Views => cols >= 1 && rows == 1 && p == [0.0; 3],
            };
            let layout = AtlasLayout {
                kind,
                cols,
                rows,
                first_frame,
            };
            if !shape_ok || first_frame != next_frame {
                return Err(FormatError::invalid(
                    "atlas layout",
                    "bad grid shape or frames out of order",
                ));
            }
            next_frame = next_frame.saturating_add(layout.frame_count());
            layouts.push(layout);
        }
        if next_frame != frame_count {
            return Err(FormatError::invalid("atlas layouts", "do not tile the frame table"));
        }
        let mut views = layouts.iter().filter(|l| l.kind == AtlasLayoutKind::Views);
        let view_frames = views.next().map_or(0, |l| l.frame_count() as usize);
        if views.next().is_some() {
            return Err(FormatError::invalid("atlas layouts", "more than one views layout"));
        }
        if Self::table_len(nres, nlay, view_frames, frame_count as usize) != table_len {
            return Err(FormatError::invalid("atlas table length", "disagrees with the counts"));
        }
        let mut view_angles = Vec::with_capacity(view_frames);
        for _ in 0..view_frames {
            let a = [
                c.finite_f32("atlas view azimuth")?,
                c.finite_f32("atlas view elevation")?,
            ];
            if !(-std::f32::consts::TAU..=std::f32::consts::TAU).contains(&a[0])
                || !(-std::f32::consts::FRAC_PI_2..=std::f32::consts::FRAC_PI_2).contains(&a[1])
            {
                return Err(FormatError::invalid(
                    "atlas view direction",
                    "azimuth outside ±2π or elevation outside ±π/2",
                ));
            }
            view_angles.push(a);
        }
        let mut frames = Vec::with_capacity(frame_count as usize);
        let mut cursor = table_len as u64;
        for _ in 0..frame_count {
            let root_u = c.finite_f32("atlas root anchor")?;
            let root_v = c.finite_f32("atlas root anchor")?;
            let mut images = Vec::with_capacity(nres);
            for _ in 0..nres {
                let e = ImageEntry {
                    offset: c.u32()?,
                    length: c.u32()?,
                    crc: c.u32()?,
                };
                if e.length == 0 {
                    if e.offset != 0 || e.crc != 0 {
                        return Err(FormatError::invalid(
                            "atlas image entry",
                            "absent image with offset or CRC",
                        ));
                    }
                } else if u64::from(e.offset) != cursor {
                    return Err(FormatError::invalid(
                        "atlas image entry",
                        format!("offset {} where {cursor} was expected", e.offset),
                    ));
                } else {
                    cursor += u64::from(e.length);
                }
                images.push(e);
            }
            let present = images.iter().filter(|e| e.length > 0).count();
            if present != 0 && present != nres {
                return Err(FormatError::invalid(
                    "atlas frame",
                    "some resolutions present, others absent",
                ));
            }
            frames.push(AtlasFrame { root_u, root_v, images });
        }
        c.finish()?;
        if cursor != section_len {
            return Err(FormatError::invalid(
                "atlas images",
                format!("end at {cursor}, section is {section_len} bytes"),
            ));
        }
        let views = (view_frames > 0).then(|| {
            let dirs: Vec<Vec3> = view_angles.iter().map(|a| lat_long_direction(a[0], a[1])).collect();
            std::sync::Arc::new(ViewSphere::new(&dirs))
        });
        Ok(Self {
            codec,
            center,
            radius,
            resolutions,
            layouts,
            frames,
            view_angles,
            views,
        })
    }

    /// The image entry of `frame` at resolution index `res`: `None` when out of range or absent.
    pub fn image(&self, frame: u32, res: usize) -> Option<ImageEntry> {
        self.frames
            .get(frame as usize)
            .and_then(|f| f.images.get(res))
            .copied()
            .filter(|e| e.length > 0)
    }

    /// Checks a fetched image against its entry (length and CRC) and returns it.
    pub fn verify_image<'a>(entry: &ImageEntry, bytes: &'a [u8]) -> Result<&'a [u8], FormatError> {
        if bytes.len() != entry.length as usize {
            return Err(FormatError::Truncated {
                what: "atlas image",
                need: u64::from(entry.length),
                have: bytes.len() as u64,
            });
        }
        check_crc("atlas image", bytes, entry.crc)?;
        Ok(bytes)
    }

    /// The verified image bytes of `frame` at resolution `res` out of the whole section.
    pub fn image_bytes<'a>(&self, section: &'a [u8], frame: u32, res: usize) -> Result<Option<&'a [u8]>, FormatError> {
        let Some(e) = self.image(frame, res) else {
            return Ok(None);
        };
        let start = e.offset as usize;
        let end = start.saturating_add(e.length as usize);
        let bytes = section.get(start..end).ok_or(FormatError::Truncated {
            what: "atlas image",
            need: end as u64,
            have: section.len() as u64,
        })?;
        Self::verify_image(&e, bytes).map(Some)
    }

    /// Camera placement of a table frame: the view direction (tree → camera).
    pub fn frame_direction(&self, frame: u32) -> Option<Vec3> {
        let l = self
            .layouts
            .iter()
            .find(|l| frame >= l.first_frame && frame - l.first_frame < l.frame_count())?;
        if l.kind == AtlasLayoutKind::Views {
            let a = self.view_angles.get((frame - l.first_frame) as usize)?;
            return Some(lat_long_direction(a[0], a[1]));
        }
        l.direction(frame - l.first_frame)
    }
}

/// Decodes a PNG frame to RGBA8 (`side × side` expected); a malformed image is a
/// [`FormatError::Invalid`].
pub fn decode_png_frame(bytes: &[u8], side: u16) -> Result<image::RgbaImage, FormatError> {
    let img = image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
        .map_err(|e| FormatError::invalid("atlas image", e.to_string()))?
        .to_rgba8();
    if img.width() != u32::from(side) || img.height() != u32::from(side) {
        return Err(FormatError::invalid(
            "atlas image",
            format!("{}x{} where {side}² was expected", img.width(), img.height()),
        ));
    }
    Ok(img)
}

/// A frame to encode: root anchor and one encoded image per resolution (empty `Vec` per
/// resolution, or no images at all, for an absent frame).
#[derive(Debug, Clone, PartialEq)]
pub struct FrameImages {
    /// See [`AtlasFrame::root_u`].
    pub root_u: f32,
    /// See [`AtlasFrame::root_v`].
    pub root_v: f32,
    /// Encoded images, one per resolution; `None` for an empty frame.
    pub images: Option<Vec<Vec<u8>>>,
}

/// Encodes an atlas section. `layouts` must tile `frames` in order (their `first_frame` is
/// recomputed here), resolutions strictly decreasing, every present frame must have one
/// image per resolution, and `view_angles` hold one (azimuth, elevation) per frame of the
/// views layout (none without one); otherwise an error, never a file a reader would reject.
pub fn encode_atlases(
    codec: AtlasCodec,
    center: Vec3,
    radius: f32,
    resolutions: &[u16],
    layouts: &[AtlasLayout],
    view_angles: &[[f32; 2]],
    frames: &[FrameImages],
) -> Result<Vec<u8>, FormatError> {
    let nres = resolutions.len();
    if !(1..=MAX_ATLAS_RESOLUTIONS).contains(&nres)
        || layouts.len() > MAX_ATLAS_LAYOUTS
        || resolutions.windows(2).any(|w| w[1] >= w[0])
        || resolutions.iter().any(|&r| r == 0 || r > MAX_ATLAS_RESOLUTION)
        || !(radius > 0.0 && radius.is_finite() && center.is_finite())
    {
        return Err(FormatError::invalid("atlas", "bad resolutions, layouts or sphere"));
    }
    let total: u32 = layouts.iter().map(AtlasLayout::frame_count).sum();
    if total as usize != frames.len() || total > MAX_ATLAS_FRAMES {
        return Err(FormatError::invalid("atlas", "layouts do not tile the frames"));
    }
    let views: Vec<&AtlasLayout> = layouts.iter().filter(|l| l.kind == AtlasLayoutKind::Views).collect();
    let view_frames = views.first().map_or(0, |l| l.frame_count() as usize);
    let angles_ok = view_angles.iter().all(|a| {
        (-std::f32::consts::TAU..=std::f32::consts::TAU).contains(&a[0])
            && (-std::f32::consts::FRAC_PI_2..=std::f32::consts::FRAC_PI_2).contains(&a[1])
    });
    if views.len() > 1 || view_angles.len() != view_frames || !angles_ok {
        return Err(FormatError::invalid(
            "atlas",
            "at most one views layout, with one direction (azimuth ±2π, elevation ±π/2) per frame",
        ));
    }
    let table_len = AtlasTable::table_len(nres, layouts.len(), view_frames, frames.len());
    let mut w = Writer::default();
    w.u32(table_len as u32);
    w.u8(codec.code());
    w.u8(nres as u8);
    w.u8(layouts.len() as u8);
    w.u8(0);
    w.u32(total);
    for v in center.to_array() {
        w.f32(v);
    }
    w.f32(radius);
    for &r in resolutions {
        w.u16(r);
    }
    let mut first = 0u32;
    for l in layouts {
        w.u8(l.kind.code());
        w.u8(0);
        w.u16(l.cols);
        w.u16(l.rows);
        w.u16(0);
        let p = match l.kind {
            AtlasLayoutKind::LatLong {
                elevation_min,
                elevation_step,
                azimuth_step,
            } => [elevation_min, elevation_step, azimuth_step],
            _ => [0.0; 3],
        };
        for v in p {
            w.f32(v);
        }
        w.u32(first);
        first += l.frame_count();
    }
    for a in view_angles {
        w.f32(a[0]);
        w.f32(a[1]);
    }
    let mut offset = table_len as u64;
    let mut images: Vec<&[u8]> = Vec::new();
    for f in frames {
        if !(f.root_u.is_finite() && f.root_v.is_finite()) {
            return Err(FormatError::invalid("atlas frame", "non-finite root anchor"));
        }
        w.f32(f.root_u);
        w.f32(f.root_v);
        match &f.images {
            None => {
                for _ in 0..nres {
                    w.u32(0);
                    w.u32(0);
                    w.u32(0);
                }
            }
            Some(imgs) => {
                if imgs.len() != nres || imgs.iter().any(Vec::is_empty) {
                    return Err(FormatError::invalid(
                        "atlas frame",
                        "needs one non-empty image per resolution",
                    ));
                }
                for img in imgs {
                    let off = u32::try_from(offset).map_err(|_| FormatError::invalid("atlas", "section over 4 GiB"))?;
                    w.u32(off);
                    w.u32(img.len() as u32);
                    w.u32(crc32(img));
                    offset += img.len() as u64;
                    images.push(img);
                }
            }
        }
    }
    let crc = crc32(&w.buf);
    w.u32(crc);
    if w.buf.len() != table_len {
        return Err(FormatError::invalid("atlas", "table length mismatch (encoder bug)"));
    }
    for img in images {
        w.buf.extend_from_slice(img);
    }
    Ok(w.buf)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn sample() -> (Vec<AtlasLayout>, Vec<FrameImages>) {
        let layouts = vec![
            AtlasLayout {
                kind: AtlasLayoutKind::LatLong {
                    elevation_min: 0.0,
                    elevation_step: 0.5,
                    azimuth_step: 1.0,
                },
                cols: 3,
                rows: 2,
                first_frame: 0,
            },
            AtlasLayout {
                kind: AtlasLayoutKind::CrossedQuads,
                cols: 2,
                rows: 1,
                first_frame: 6,
            },
        ];
        let frames = (0..8)
            .map(|i| FrameImages {
                root_u: 0.5,
                root_v: 0.1 * i as f32,
                images: (i != 3).then(|| vec![vec![i as u8; 10 + i], vec![7; 3]]),
            })
            .collect();
        (layouts, frames)
    }

    #[test]
    fn round_trip_and_single_frame_fetch() {
        let (layouts, frames) = sample();
        let bytes = encode_atlases(
            AtlasCodec::Png,
            Vec3::new(0.0, 2.0, 0.0),
            3.0,
            &[32, 16],
            &layouts,
            &[],
            &frames,
        )
        .unwrap();
        let table_len = AtlasTable::peek_table_len(&bytes).unwrap() as usize;
        let t = AtlasTable::decode(&bytes[..table_len], bytes.len() as u64).unwrap();
        assert_eq!(t.layouts, layouts);
        assert_eq!(t.frames.len(), 8);
        assert!(!t.frames[3].is_present());
        assert_eq!(t.image(3, 0), None);
        for (i, f) in frames.iter().enumerate() {
            assert_eq!(t.frames[i].root_v, f.root_v);
            for r in 0..2 {
                let got = t.image_bytes(&bytes, i as u32, r).unwrap();
                assert_eq!(got.map(<[u8]>::to_vec), f.images.as_ref().map(|v| v[r].clone()));
            }
        }
        // A single fetched frame verifies alone.
        let e = t.image(5, 0).unwrap();
        let one = &bytes[e.offset as usize..(e.offset + e.length) as usize];
        AtlasTable::verify_image(&e, one).unwrap();
        let mut bad = one.to_vec();
        bad[0] ^= 1;
        assert!(AtlasTable::verify_image(&e, &bad).is_err());
        assert_eq!(t.frame_direction(6).unwrap(), lat_long_direction(0.0, 0.0));
    }

    #[test]
    fn corrupt_sections_are_rejected() {
        let (layouts, frames) = sample();
        let bytes = encode_atlases(AtlasCodec::Png, Vec3::ZERO, 1.0, &[8], &layouts, &[], &{
            frames
                .iter()
                .map(|f| FrameImages {
                    images: f.images.as_ref().map(|v| vec![v[0].clone()]),
                    ..f.clone()
                })
                .collect::<Vec<_>>()
        })
        .unwrap();
        for n in 0..bytes.len() {
            let _ = AtlasTable::decode(&bytes[..n], bytes.len() as u64);
            assert!(AtlasTable::decode(&bytes[..n], n as u64).is_err(), "prefix {n}");
        }
        let table_len = AtlasTable::peek_table_len(&bytes).unwrap() as usize;
        for i in 0..table_len {
            for bit in [0u8, 3, 7] {
                let mut b = bytes.clone();
                b[i] ^= 1 << bit;
                assert!(AtlasTable::decode(&b, b.len() as u64).is_err(), "flip at {i}");
            }
        }
        // Image bytes flipped: the table is fine, the frame fails its CRC.
        let t = AtlasTable::decode(&bytes, bytes.len() as u64).unwrap();
        let mut b = bytes.clone();
        let last = b.len() - 1;
        b[last] ^= 0x10;
        assert!(t.image_bytes(&b, 7, 0).is_err());
        assert!(t.image_bytes(&b[..last], 7, 0).is_err());
        assert!(AtlasTable::decode(&bytes, bytes.len() as u64 + 1).is_err());
        assert!(decode_png_frame(&bytes, 8).is_err());
    }

    #[test]
    fn encoder_rejects_inconsistent_input() {
        let (layouts, frames) = sample();
        assert!(encode_atlases(AtlasCodec::Png, Vec3::ZERO, 1.0, &[16, 32], &layouts, &[], &frames).is_err());
        assert!(encode_atlases(AtlasCodec::Png, Vec3::ZERO, 1.0, &[32], &layouts, &[], &frames).is_err());
        assert!(encode_atlases(AtlasCodec::Png, Vec3::ZERO, 0.0, &[32, 16], &layouts, &[], &frames).is_err());
        assert!(encode_atlases(AtlasCodec::Png, Vec3::ZERO, 1.0, &[32, 16], &layouts[..1], &[], &frames).is_err());
    }

    /// A views layout after a crossed one: its directions round-trip, its triangulation is
    /// built, and bad direction blocks are refused by the encoder and the decoder.
    #[test]
    fn views_layout_round_trips_and_is_checked() {
        let layouts = vec![
            AtlasLayout {
                kind: AtlasLayoutKind::CrossedQuads,
                cols: 2,
                rows: 1,
                first_frame: 0,
            },
            AtlasLayout {
                kind: AtlasLayoutKind::Views,
                cols: 5,
                rows: 1,
                first_frame: 2,
            },
        ];
        let angles = [[0.0, 0.0], [1.5, 0.2], [3.0, 0.1], [-1.6, 0.3], [0.4, 1.2]];
        let frames: Vec<FrameImages> = (0..7)
            .map(|i| FrameImages {
                root_u: 0.5,
                root_v: 0.0,
                images: Some(vec![vec![i as u8; 5]]),
            })
            .collect();
        let enc =
            |l: &[AtlasLayout], a: &[[f32; 2]]| encode_atlases(AtlasCodec::Png, Vec3::ZERO, 1.0, &[8], l, a, &frames);
        let bytes = enc(&layouts, &angles).unwrap();
        let t = AtlasTable::decode(&bytes, bytes.len() as u64).unwrap();
        assert_eq!(t.view_angles, angles.to_vec());
        assert_eq!(t.layouts[1].kind.name(), "views");
        assert_eq!(t.frame_direction(3).unwrap(), lat_long_direction(1.5, 0.2));
        assert_eq!(t.layouts[1].direction(0), None);
        let v = t.views.as_ref().unwrap();
        assert_eq!(v.len(), 5);
        // Seen from frame 4's own direction, frame 4 (local) is the nearest.
        assert_eq!(v.nearest(lat_long_direction(0.4, 1.2), 0).map(|x| x.0), Some(4));
        // Encoder: wrong count, out-of-range elevation, two views layouts.
        assert!(enc(&layouts, &angles[..4]).is_err());
        assert!(enc(&layouts, &[[0.0, 0.0], [1.5, 0.2], [3.0, 0.1], [-1.6, 0.3], [0.4, 1.6]]).is_err());
        assert!(enc(&layouts[..1], &angles).is_err());
        // Decoder: every truncation and bit flip of the table is an error, never a panic.
        let tl = AtlasTable::peek_table_len(&bytes).unwrap() as usize;
        for i in 0..tl {
            let mut b = bytes.clone();
            b[i] ^= 0x04;
            assert!(AtlasTable::decode(&b, b.len() as u64).is_err(), "flip at {i}");
        }
        // An elevation past ±π/2 with a valid CRC: refused by name.
        let mut b = bytes.clone();
        let off = ATLAS_HEADER_LEN + 2 + 2 * ATLAS_LAYOUT_LEN + 4;
        b[off..off + 4].copy_from_slice(&2.0f32.to_le_bytes());
        let crc = crc32(&b[..tl - 4]);
        b[tl - 4..tl].copy_from_slice(&crc.to_le_bytes());
        let e = AtlasTable::decode(&b, b.len() as u64).unwrap_err().to_string();
        assert!(e.contains("atlas view direction"), "{e}");
    }
}
