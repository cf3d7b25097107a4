//! Textures against the table: one plane's bytes checked (length, CRC-32) or decoded to RGBA8,
//! a whole level checked or decoded from its single byte range, a plane's bytes cut from the
//! whole section, and [`decode_clouds`] (table plus every texture's CRC).

use super::table::{CloudPlane, CloudTable};
use crate::format::{FormatError, check_crc};

impl CloudTable {
    /// Checks fetched texture bytes against the plane's entry (length, CRC) and returns them.
    pub fn verify_texture<'a>(plane: &CloudPlane, bytes: &'a [u8]) -> Result<&'a [u8], FormatError> {
        if bytes.len() as u64 != u64::from(plane.texture.length) {
            return Err(FormatError::Truncated {
                what: "cloud texture",
                need: u64::from(plane.texture.length),
                have: bytes.len() as u64,
            });
        }
        check_crc("cloud texture", bytes, plane.texture.crc)?;
        Ok(bytes)
    }

    /// Verifies and decodes one plane's texture to RGBA8 of the recorded size.
    pub fn decode_texture(plane: &CloudPlane, bytes: &[u8]) -> Result<image::RgbaImage, FormatError> {
        let bytes = Self::verify_texture(plane, bytes)?;
        let img = image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
            .map_err(|e| FormatError::CloudImage(e.to_string()))?
            .to_rgba8();
        if img.width() != u32::from(plane.width) || img.height() != u32::from(plane.height) {
            return Err(FormatError::CloudImage(format!(
                "{}x{} where {}x{} was recorded",
                img.width(),
                img.height(),
                plane.width,
                plane.height
            )));
        }
        Ok(img)
    }

    /// Checks the bytes of [`CloudTable::level_range`] (fetched in one request) against every
    /// plane's length and CRC-32, without decoding the PNGs: what a client checks before it
    /// caches a level.
    pub fn verify_level(&self, level: usize, level_bytes: &[u8]) -> Result<(), FormatError> {
        self.level_textures(level, level_bytes)?
            .try_for_each(|(p, b)| Self::verify_texture(p, b).map(|_| ()))
    }

    /// Each plane of level `level` with its texture bytes cut from the level's bytes (length
    /// checked; CRCs not).
    fn level_textures<'s, 'b>(
        &'s self,
        level: usize,
        level_bytes: &'b [u8],
    ) -> Result<impl Iterator<Item = (&'s CloudPlane, &'b [u8])> + use<'s, 'b>, FormatError> {
        let l = self
            .levels
            .get(level)
            .ok_or_else(|| FormatError::CloudCounts(format!("level {level} of {}", self.levels.len())))?;
        if level_bytes.len() as u64 != u64::from(l.textures.length) {
            return Err(FormatError::Truncated {
                what: "cloud level",
                need: u64::from(l.textures.length),
                have: level_bytes.len() as u64,
            });
        }
        let base = u64::from(l.textures.offset);
        Ok(self.level_planes(level).iter().map(move |p| {
            let r = p.texture.range();
            // In bounds: decode checked that the planes tile the level's range.
            (p, &level_bytes[(r.start - base) as usize..(r.end - base) as usize])
        }))
    }

    /// Decodes every texture of level `level` from the bytes of [`CloudTable::level_range`]
    /// (fetched in one request): one image per plane, in plane order.
    pub fn decode_level(&self, level: usize, level_bytes: &[u8]) -> Result<Vec<image::RgbaImage>, FormatError> {
        self.level_textures(level, level_bytes)?
            .map(|(p, b)| Self::decode_texture(p, b))
            .collect()
    }

    /// The verified texture bytes of section-wide plane `plane` out of the whole section.
    pub fn texture_bytes<'a>(&self, section: &'a [u8], plane: usize) -> Result<&'a [u8], FormatError> {
        let p = self
            .planes
            .get(plane)
            .ok_or_else(|| FormatError::CloudCounts(format!("plane {plane} of {}", self.planes.len())))?;
        let r = p.texture.range();
        let bytes = section
            .get(r.start as usize..r.end as usize)
            .ok_or(FormatError::Truncated {
                what: "cloud texture",
                need: r.end,
                have: section.len() as u64,
            })?;
        Self::verify_texture(p, bytes)
    }
}

/// Decodes a whole section: the table and every texture's CRC (not the PNGs).
pub fn decode_clouds(section: &[u8]) -> Result<CloudTable, FormatError> {
    let t = CloudTable::decode(section, section.len() as u64)?;
    for i in 0..t.planes.len() {
        t.texture_bytes(section, i)?;
    }
    Ok(t)
}
