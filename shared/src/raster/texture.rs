//! RGBA8 textures: sRGB colour + linear alpha, nearest/bilinear sampling, alpha test.

use std::path::Path;

use glam::{Vec2, Vec4};

use super::RasterError;

/// Index of a texture in [`Scene::textures`](super::Scene::textures).
pub type TextureId = u32;

/// Sampling filter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Filter {
    /// The texel whose area contains the sample point.
    Nearest,
    /// Bilinear between the four nearest texel centres.
    #[default]
    Bilinear,
}

/// Addressing outside `[0, 1]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Wrap {
    /// Clamp to the edge texels.
    #[default]
    Clamp,
    /// Repeat (tile).
    Repeat,
}

/// An RGBA8 texture. Row 0 is the top row of the image and has `v = 0` (glTF convention, as
/// the uvs of [`crate::tessellate::leaf_quads`]); `u = 0` is the left column.
#[derive(Debug, Clone, PartialEq)]
pub struct Texture {
    width: u32,
    height: u32,
    /// Texels row-major; rgb decoded to linear, alpha in [0, 1].
    linear: Vec<Vec4>,
    /// How to sample.
    pub filter: Filter,
    /// How to address outside [0, 1].
    pub wrap: Wrap,
}

/// sRGB-encoded byte → linear [0, 1].
pub(crate) fn srgb_to_linear(c: u8) -> f32 {
    let c = f32::from(c) / 255.0;
    if c <= 0.040_45 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Entries of the linear → sRGB table (12-bit input precision).
const SRGB_LUT_SIZE: usize = 4096;

/// Linear → sRGB table; built once (powf per pixel was a visible share of shading time).
static SRGB_LUT: std::sync::LazyLock<Vec<u8>> = std::sync::LazyLock::new(|| {
    (0..SRGB_LUT_SIZE)
        .map(|i| linear_to_srgb_exact(i as f32 / (SRGB_LUT_SIZE - 1) as f32))
        .collect()
});

/// Linear [0, 1] → sRGB-encoded byte (rounded, clamped), exact formula.
fn linear_to_srgb_exact(c: f32) -> u8 {
    let c = c.clamp(0.0, 1.0);
    let s = if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5) as u8
}

/// Linear [0, 1] → sRGB-encoded byte via a 4096-entry table (clamped; NaN → 0). Within one
/// step of the exact value; exact for the decoded value of every byte.
pub(crate) fn linear_to_srgb(c: f32) -> u8 {
    let i = (c.clamp(0.0, 1.0) * (SRGB_LUT_SIZE - 1) as f32 + 0.5) as usize;
    SRGB_LUT.get(i).copied().unwrap_or(0)
}

impl Texture {
    /// A texture from row-major RGBA8 texels (sRGB colour, linear alpha).
    /// Errors if `pixels.len() != width × height` or a side is zero.
    pub fn new(width: u32, height: u32, pixels: &[[u8; 4]]) -> Result<Self, RasterError> {
        if width == 0 || height == 0 || pixels.len() != width as usize * height as usize {
            return Err(RasterError::InvalidTexture(format!(
                "{width}x{height} with {} texels",
                pixels.len()
            )));
        }
        let lut: Vec<f32> = (0..=255u8).map(srgb_to_linear).collect();
        let linear = pixels
            .iter()
            .map(|p| {
                Vec4::new(
                    lut[p[0] as usize],
                    lut[p[1] as usize],
                    lut[p[2] as usize],
                    f32::from(p[3]) / 255.0,
                )
            })
            .collect();
        Ok(Self {
            width,
            height,
            linear,
            filter: Filter::default(),
            wrap: Wrap::default(),
        })
    }

    /// A texture from an `image` RGBA8 buffer.
    pub fn from_image(img: &image::RgbaImage) -> Result<Self, RasterError> {
        let px: Vec<[u8; 4]> = img.pixels().map(|p| p.0).collect();
        Self::new(img.width(), img.height(), &px)
    }

    /// Loads a PNG (any colour type, converted to RGBA8).
    pub fn load_png(path: &Path) -> Result<Self, RasterError> {
        let img = image::ImageReader::open(path)
            .map_err(image::ImageError::IoError)?
            .with_guessed_format()
            .map_err(image::ImageError::IoError)?
            .decode()?;
        Self::from_image(&img.to_rgba8())
    }

    /// A 1×1 texture of one colour.
    pub fn solid(rgba: [u8; 4]) -> Self {
        Self {
            width: 1,
            height: 1,
            linear: vec![Vec4::new(
                srgb_to_linear(rgba[0]),
                srgb_to_linear(rgba[1]),
                srgb_to_linear(rgba[2]),
                f32::from(rgba[3]) / 255.0,
            )],
            filter: Filter::Nearest,
            wrap: Wrap::Clamp,
        }
    }

    /// A procedural leaf mask of `size × size` texels (for tests and benches): white, opaque
    /// inside the ellipse inscribed in the unit square pinched towards `v = 0` and `v = 1`,
    /// transparent outside. About 60 % of the texels are opaque.
    pub fn procedural_leaf(size: u32) -> Self {
        let size = size.max(1);
        let px = Self::procedural_leaf_rgba(size);
        let mut t = Self::new(size, size, &px).unwrap_or_else(|_| Self::solid([255; 4]));
        t.filter = Filter::Nearest;
        t
    }

    /// The texels of [`Texture::procedural_leaf`], row-major from `v = 0`, for GPU uploads
    /// that must match the CPU rasterizer.
    pub fn procedural_leaf_rgba(size: u32) -> Vec<[u8; 4]> {
        let size = size.max(1);
        let mut px = Vec::with_capacity((size * size) as usize);
        for y in 0..size {
            for x in 0..size {
                let u = (x as f32 + 0.5) / size as f32 * 2.0 - 1.0;
                let v = (y as f32 + 0.5) / size as f32 * 2.0 - 1.0;
                // A lens shape: half-width shrinks towards both ends.
                let half_width = (1.0 - v * v).max(0.0).sqrt() * (1.0 - 0.3 * v.abs());
                let a = if u.abs() <= half_width { 255 } else { 0 };
                px.push([255, 255, 255, a]);
            }
        }
        px
    }

    /// Width in texels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in texels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Texel at integer coordinates after wrapping; linear rgb, alpha in [0, 1].
    fn texel(&self, x: i64, y: i64) -> Vec4 {
        let (w, h) = (i64::from(self.width), i64::from(self.height));
        let (x, y) = match self.wrap {
            Wrap::Clamp => (x.clamp(0, w - 1), y.clamp(0, h - 1)),
            Wrap::Repeat => (x.rem_euclid(w), y.rem_euclid(h)),
        };
        self.linear[(y * w + x) as usize]
    }

    /// Samples at `uv` with this texture's filter and wrap: linear rgb and alpha in [0, 1].
    /// Non-finite uvs sample texel (0, 0).
    pub fn sample(&self, uv: Vec2) -> Vec4 {
        let uv = if uv.is_finite() { uv } else { Vec2::ZERO };
        let x = uv.x * self.width as f32;
        let y = uv.y * self.height as f32;
        match self.filter {
            Filter::Nearest => self.texel(x.floor() as i64, y.floor() as i64),
            Filter::Bilinear => {
                let (fx, fy) = (x - 0.5, y - 0.5);
                let (x0, y0) = (fx.floor(), fy.floor());
                let (tx, ty) = (fx - x0, fy - y0);
                let (x0, y0) = (x0 as i64, y0 as i64);
                let top = self.texel(x0, y0).lerp(self.texel(x0 + 1, y0), tx);
                let bottom = self.texel(x0, y0 + 1).lerp(self.texel(x0 + 1, y0 + 1), tx);
                top.lerp(bottom, ty)
            }
        }
    }

    /// Alpha test: `true` if the sampled alpha at `uv` is at least `cutoff`.
    pub fn alpha_test(&self, uv: Vec2, cutoff: f32) -> bool {
        self.sample(uv).w >= cutoff
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn sampling_and_alpha_test() {
        // 2×1: left opaque red, right transparent.
        let mut t = Texture::new(2, 1, &[[255, 0, 0, 255], [0, 0, 0, 0]]).unwrap();
        t.filter = Filter::Nearest;
        assert_eq!(t.sample(Vec2::new(0.25, 0.5)), Vec4::new(1.0, 0.0, 0.0, 1.0));
        assert!(t.alpha_test(Vec2::new(0.2, 0.5), 0.5));
        assert!(!t.alpha_test(Vec2::new(0.8, 0.5), 0.5));
        t.filter = Filter::Bilinear;
        let mid = t.sample(Vec2::new(0.5, 0.5));
        assert!((mid.w - 0.5).abs() < 1e-6);
        // Clamp at the edges.
        assert_eq!(t.sample(Vec2::new(-3.0, 0.5)).w, 1.0);
        t.wrap = Wrap::Repeat;
        t.filter = Filter::Nearest;
        assert_eq!(t.sample(Vec2::new(1.25, 0.5)).w, 1.0);
        assert!(Texture::new(2, 2, &[[0; 4]]).is_err());
        for c in [0u8, 1, 10, 128, 200, 255] {
            assert_eq!(linear_to_srgb(srgb_to_linear(c)), c);
        }
    }
}
