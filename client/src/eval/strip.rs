//! Image strips: a method's rendering, the full-detail reference and the FLIP error map side by
//! side in one PNG, so that what the metrics say can be checked by eye.
//!
//! Conventions: panels are the rendered views composited over [`super::BACKGROUND`], left to
//! right method | reference | error (magma: black = no error, pale yellow = largest), separated
//! by [`GAP_PX`] white columns; row 0 at the top.

use std::path::Path;

use canopy_shared::metrics::{magma, write_png};

use super::{BACKGROUND, EvalError, View};

/// White columns between panels.
pub const GAP_PX: u32 = 4;

/// Writes `view | reference | error map` to `path` (a PNG). `flip_map` holds one error per pixel
/// of the views (all three the same size).
pub fn write_strip(path: &Path, view: &View, reference: &View, flip_map: &[f32]) -> Result<(), EvalError> {
    let (w, h) = (view.width, view.height);
    let n = w as usize * h as usize;
    if reference.width != w || reference.height != h || view.color.len() != n || reference.color.len() != n {
        return Err(EvalError::Strip(format!(
            "views of {w}x{h} and {}x{} pixels",
            reference.width, reference.height
        )));
    }
    if flip_map.len() != n {
        return Err(EvalError::Strip(format!("{} errors for {n} pixels", flip_map.len())));
    }
    let over = |p: [u8; 4]| {
        let a = u32::from(p[3]);
        let c = |i: usize| ((u32::from(p[i]) * a + u32::from(BACKGROUND[i]) * (255 - a) + 127) / 255) as u8;
        [c(0), c(1), c(2), 255]
    };
    let sw = 3 * w + 2 * GAP_PX;
    let mut out = vec![[255u8; 4]; sw as usize * h as usize];
    for y in 0..h as usize {
        for x in 0..w as usize {
            let i = y * w as usize + x;
            let row = y * sw as usize;
            let e = magma(flip_map[i]);
            out[row + x] = over(view.color[i]);
            out[row + (w + GAP_PX) as usize + x] = over(reference.color[i]);
            out[row + 2 * (w + GAP_PX) as usize + x] = [e[0], e[1], e[2], 255];
        }
    }
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    write_png(path, sw, h, &out)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view(c: [u8; 4]) -> View {
        View {
            width: 6,
            height: 4,
            color: vec![c; 24],
            covered: vec![c[3] > 0; 24],
            triangles: 0,
        }
    }

    #[test]
    fn strip_holds_three_panels() {
        let dir = std::env::temp_dir().join(format!("canopy-strip-{}", std::process::id()));
        let path = dir.join("nested/s.png");
        let (v, r) = (view([200, 0, 0, 255]), view([0, 0, 0, 0]));
        let err = vec![1.0; 24];
        write_strip(&path, &v, &r, &err).expect("strip");
        let img = image::open(&path).expect("png").to_rgba8();
        assert_eq!(img.dimensions(), (3 * 6 + 2 * GAP_PX, 4));
        assert_eq!(img.get_pixel(0, 0).0, [200, 0, 0, 255]);
        // Transparent reference pixels show the sky.
        assert_eq!(img.get_pixel(6 + GAP_PX, 0).0[..3], BACKGROUND);
        assert_eq!(img.get_pixel(6, 0).0, [255; 4]);
        let e = magma(1.0);
        assert_eq!(img.get_pixel(2 * (6 + GAP_PX), 3).0, [e[0], e[1], e[2], 255]);
        assert!(write_strip(&path, &v, &r, &err[1..]).is_err());
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }
}
