//! Tests of heightmap import, on images made here with the PNG and TIFF encoders: round trips,
//! and each bad input refused with an error that names what it found.

use std::io::Cursor;

use image::ImageEncoder;
use image::codecs::png::PngEncoder;
use tiff::encoder::{TiffEncoder, colortype};
use tiff::tags::Tag;

use super::*;

fn png(w: u32, h: u32, color: image::ExtendedColorType, bytes: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    PngEncoder::new(&mut out)
        .write_image(bytes, w, h, color)
        .expect("encode PNG");
    out
}

/// A 16-bit grayscale PNG of `w × h` with value `f(i, j)`.
fn png16(w: u32, h: u32, f: impl Fn(u32, u32) -> u16) -> Vec<u8> {
    let bytes: Vec<u8> = (0..h)
        .flat_map(|j| (0..w).map(move |i| (i, j)))
        .flat_map(|(i, j)| f(i, j).to_ne_bytes())
        .collect();
    png(w, h, image::ExtendedColorType::L16, &bytes)
}

fn opts(cell: f64, heights: Option<[f32; 2]>) -> ImportOptions {
    ImportOptions {
        cell: Some(cell),
        heights,
        ..ImportOptions::default()
    }
}

fn message(e: &ImportError) -> String {
    e.to_string()
}

#[test]
fn a_16_bit_png_round_trips() {
    let (w, h) = (70, 40);
    let value = |i: u32, j: u32| ((i * 900 + j * 50) % 65_536) as u16;
    let bytes = png16(w, h, value);
    let got = import(&bytes, &opts(2.0, Some([-10.0, 55.535]))).expect("imports");
    assert_eq!(got.format, HeightmapFormat::Png);
    assert_eq!(got.sample, "u16");
    let g = got.field.grid;
    assert_eq!(g.samples, [70, 40]);
    assert_eq!(g.cell, 2.0);
    // Centred on the origin by default.
    assert_eq!(g.origin, [-69.0, -39.0]);
    for (i, j) in [(0, 0), (69, 0), (0, 39), (33, 17), (69, 39)] {
        let want = -10.0 + 65.535 * f32::from(value(i, j)) / 65_535.0;
        assert!(
            (got.field.at(i, j) - want).abs() < 2e-3,
            "({i}, {j}): {} vs {want}",
            got.field.at(i, j)
        );
    }
    // Rows run along +z: sample (i, j) stands at origin + (i, j)·cell.
    let (x, z) = (g.origin[0] + 2.0 * 33.0, g.origin[1] + 2.0 * 17.0);
    assert!((got.field.height_at(x as f32, z as f32) - got.field.at(33, 17)).abs() < 1e-3);
    // Through the file format and back.
    assert_eq!(Heightfield::decode(&got.field.encode()).expect("decodes"), got.field);
    // An origin given, and the size asked for.
    let o = ImportOptions {
        origin: Some([100.0, -5.0]),
        samples: Some([70, 40]),
        ..opts(2.0, Some([0.0, 1.0]))
    };
    assert_eq!(import(&bytes, &o).expect("imports").field.grid.origin, [100.0, -5.0]);
}

#[test]
fn an_8_bit_or_colour_png_is_refused_naming_what_it_is() {
    let gray8 = png(4, 4, image::ExtendedColorType::L8, &[7; 16]);
    let e = import(&gray8, &opts(1.0, Some([0.0, 1.0]))).expect_err("8-bit");
    assert!(matches!(e, ImportError::Depth(_)), "{e:?}");
    assert!(
        message(&e).contains("8-bit grayscale") && message(&e).contains("16-bit"),
        "{e}"
    );
    let rgb = png(4, 4, image::ExtendedColorType::Rgb8, &[7; 48]);
    let e = import(&rgb, &opts(1.0, Some([0.0, 1.0]))).expect_err("RGB");
    assert!(message(&e).contains("8-bit RGB colour"), "{e}");
    let rgb16: Vec<u8> = std::iter::repeat_n(1000u16.to_ne_bytes(), 48).flatten().collect();
    let e = import(
        &png(4, 4, image::ExtendedColorType::Rgb16, &rgb16),
        &opts(1.0, Some([0.0, 1.0])),
    )
    .expect_err("RGB16");
    assert!(message(&e).contains("16-bit RGB colour"), "{e}");
    let la16: Vec<u8> = std::iter::repeat_n(1000u16.to_ne_bytes(), 32).flatten().collect();
    let e = import(
        &png(4, 4, image::ExtendedColorType::La16, &la16),
        &opts(1.0, Some([0.0, 1.0])),
    )
    .expect_err("gray + alpha");
    assert!(message(&e).contains("grayscale with alpha"), "{e}");
}

#[test]
fn a_heightmap_of_the_wrong_size_is_refused() {
    let bytes = png16(30, 20, |i, _| i as u16);
    let o = ImportOptions {
        samples: Some([32, 20]),
        ..opts(1.0, Some([0.0, 10.0]))
    };
    let e = import(&bytes, &o).expect_err("wrong size");
    assert!(matches!(e, ImportError::Size(_)));
    assert_eq!(message(&e), "the heightmap is 30 × 20 samples, expected 32 × 20");
    // Too small to make a cell.
    let e = import(&png16(1, 9, |_, _| 0), &opts(1.0, Some([0.0, 1.0]))).expect_err("1 wide");
    assert!(message(&e).contains("at least 2 × 2"), "{e}");
}

#[test]
fn missing_or_bad_options_are_refused() {
    let bytes = png16(8, 8, |i, j| (i * j) as u16);
    let e = import(&bytes, &opts(1.0, None)).expect_err("no range");
    assert!(message(&e).contains("--heights MIN:MAX"), "{e}");
    let e = import(
        &bytes,
        &ImportOptions {
            heights: Some([0.0, 1.0]),
            ..ImportOptions::default()
        },
    )
    .expect_err("no cell");
    assert!(message(&e).contains("--cell"), "{e}");
    for bad in [[5.0, 5.0], [9.0, 1.0], [f32::NAN, 1.0], [0.0, f32::INFINITY]] {
        assert!(import(&bytes, &opts(1.0, Some(bad))).is_err(), "{bad:?}");
    }
    for cell in [0.0, -1.0, f64::NAN, 1e9] {
        assert!(import(&bytes, &opts(cell, Some([0.0, 1.0]))).is_err(), "cell {cell}");
    }
    assert!(matches!(
        import(b"GIF89a......", &opts(1.0, None)),
        Err(ImportError::Unknown)
    ));
    assert!(matches!(import(b"", &opts(1.0, None)), Err(ImportError::Unknown)));
}

/// A PNG header declaring `w × h` 16-bit grayscale pixels, with no image data.
fn png_header(w: u32, h: u32) -> Vec<u8> {
    let mut ihdr = b"IHDR".to_vec();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[16, 0, 0, 0, 0]);
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    out.extend_from_slice(&13u32.to_be_bytes());
    out.extend_from_slice(&ihdr);
    out.extend_from_slice(&crc32fast::hash(&ihdr).to_be_bytes());
    out
}

#[test]
fn truncated_and_huge_pngs_are_errors_not_panics() {
    let bytes = png16(64, 64, |i, j| (i * 1000 + j) as u16);
    let o = opts(1.0, Some([0.0, 100.0]));
    for n in [0, 8, 20, 33, 50, bytes.len() / 2, bytes.len() - 40] {
        assert!(import(&bytes[..n], &o).is_err(), "{n} bytes");
    }
    // Every flipped byte is an error or a valid import, never a panic.
    for k in (0..bytes.len()).step_by(7) {
        let mut b = bytes.clone();
        b[k] ^= 0xA5;
        let _ = import(&b, &o);
    }
    // Dimensions past the limits are refused from the header, before any allocation.
    let e = import(&png_header(100_000, 100_000), &o).expect_err("huge");
    assert!(matches!(e, ImportError::Size(_) | ImportError::Png(_)), "{e:?}");
    let e = import(&png_header(5000, 5000), &o).expect_err("over the sample count");
    assert!(message(&e).contains("at most"), "{e}");
}

fn tiff_f32(w: u32, h: u32, data: &[f32], scale: Option<[f64; 3]>, tie: Option<[f64; 6]>) -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut enc = TiffEncoder::new(Cursor::new(&mut out)).expect("encoder");
        let mut img = enc.new_image::<colortype::Gray32Float>(w, h).expect("image");
        if let Some(s) = scale {
            img.encoder()
                .write_tag(Tag::ModelPixelScaleTag, &s[..])
                .expect("scale tag");
        }
        if let Some(t) = tie {
            img.encoder().write_tag(Tag::ModelTiepointTag, &t[..]).expect("tie tag");
        }
        img.write_data(data).expect("data");
    }
    out
}

#[test]
fn a_geotiff_of_f32_samples_gives_its_cell_and_origin() {
    let (w, h) = (50, 30);
    let data: Vec<f32> = (0..w * h).map(|k| 100.0 + (k % 97) as f32 * 0.25).collect();
    let bytes = tiff_f32(
        w,
        h,
        &data,
        Some([5.0, 5.0, 0.0]),
        Some([0.0, 0.0, 0.0, 1000.0, 2000.0, 0.0]),
    );
    let got = import(&bytes, &ImportOptions::default()).expect("imports");
    assert_eq!((got.format, got.sample, got.filled), (HeightmapFormat::Tiff, "f32", 0));
    let g = got.field.grid;
    assert_eq!((g.samples, g.cell), ([50, 30], 5.0));
    // North-up: model Y falls along the rows, z = −Y rises.
    assert_eq!(g.origin, [1000.0, -2000.0]);
    for k in [0usize, 1, 777, 1499] {
        let (i, j) = ((k % 50) as u32, (k / 50) as u32);
        assert!((got.field.at(i, j) - data[k]).abs() < 1e-3, "sample {k}");
    }
    // The caller's cell and origin win over the tags.
    let o = ImportOptions {
        cell: Some(2.0),
        origin: Some([0.0, 0.0]),
        ..ImportOptions::default()
    };
    let g = import(&bytes, &o).expect("imports").field.grid;
    assert_eq!((g.cell, g.origin), (2.0, [0.0, 0.0]));
    // Without a pixel scale, the cell must be given.
    let plain = tiff_f32(w, h, &data, None, None);
    let e = import(&plain, &ImportOptions::default()).expect_err("no cell");
    assert!(message(&e).contains("--cell"), "{e}");
    assert_eq!(
        import(&plain, &opts(3.0, None)).expect("with a cell").field.grid.origin,
        [-73.5, -43.5]
    );
    // Degrees, not metres; and non-square pixels.
    let deg = tiff_f32(w, h, &data, Some([0.000_277, 0.000_277, 0.0]), None);
    assert!(message(&import(&deg, &ImportOptions::default()).expect_err("degrees")).contains("degrees"));
    let oblong = tiff_f32(w, h, &data, Some([5.0, 10.0, 0.0]), None);
    assert!(message(&import(&oblong, &ImportOptions::default()).expect_err("oblong")).contains("square"));
    // A height range is for 16-bit unsigned samples only.
    assert!(
        import(
            &bytes,
            &ImportOptions {
                heights: Some([0.0, 1.0]),
                ..ImportOptions::default()
            }
        )
        .is_err()
    );
}

#[test]
fn no_data_samples_are_filled_and_all_no_data_is_refused() {
    let mut data = vec![3.0f32; 16];
    data[5] = f32::NAN;
    data[6] = 1.5;
    let got = import(&tiff_f32(4, 4, &data, None, None), &opts(1.0, None)).expect("imports");
    assert_eq!(got.filled, 1);
    assert_eq!(got.field.at(1, 1), 1.5, "filled with the lowest valid height");
    let e = import(&tiff_f32(4, 4, &[f32::NAN; 16], None, None), &opts(1.0, None)).expect_err("all NaN");
    assert!(message(&e).contains("no-data"), "{e}");
}

#[test]
fn i16_and_u16_geotiffs_are_read_as_metres() {
    let mut out = Vec::new();
    {
        let mut enc = TiffEncoder::new(Cursor::new(&mut out)).expect("encoder");
        let data: Vec<i16> = (0..12).map(|k| -20 + 10 * k).collect();
        enc.write_image::<colortype::GrayI16>(4, 3, &data).expect("i16");
    }
    let got = import(&out, &opts(10.0, None)).expect("i16");
    assert_eq!(
        (got.sample, got.field.at(0, 0), got.field.at(3, 2)),
        ("i16", -20.0, 90.0)
    );
    let mut out = Vec::new();
    {
        let mut enc = TiffEncoder::new(Cursor::new(&mut out)).expect("encoder");
        enc.write_image::<colortype::Gray16>(3, 3, &[0, 1, 2, 3, 4, 5, 6, 7, 65_535])
            .expect("u16");
    }
    let got = import(&out, &opts(1.0, None)).expect("u16");
    assert_eq!((got.sample, got.field.at(2, 2)), ("u16", 65_535.0));
    let got = import(&out, &opts(1.0, Some([0.0, 10.0]))).expect("u16 mapped");
    assert!((got.field.at(2, 2) - 10.0).abs() < 1e-3);
}

#[test]
fn multi_band_8_bit_and_other_sample_tiffs_are_refused() {
    type Encoder<'a> = TiffEncoder<Cursor<&'a mut Vec<u8>>>;
    let tiff_of = |write: &dyn Fn(&mut Encoder<'_>)| {
        let mut out = Vec::new();
        write(&mut TiffEncoder::new(Cursor::new(&mut out)).expect("encoder"));
        out
    };
    let rgb = tiff_of(&|e| e.write_image::<colortype::RGB16>(2, 2, &[1; 12]).expect("rgb"));
    let e = import(&rgb, &opts(1.0, None)).expect_err("3 bands");
    assert!(matches!(e, ImportError::Depth(_)));
    assert!(message(&e).contains("3 bands"), "{e}");
    let rgba = tiff_of(&|e| e.write_image::<colortype::RGBA8>(2, 2, &[1; 16]).expect("rgba"));
    assert!(message(&import(&rgba, &opts(1.0, None)).expect_err("4 bands")).contains("4 bands"));
    let gray8 = tiff_of(&|e| e.write_image::<colortype::Gray8>(2, 2, &[1; 4]).expect("gray8"));
    assert!(message(&import(&gray8, &opts(1.0, None)).expect_err("8-bit")).contains("8-bit"));
    let u32s = tiff_of(&|e| e.write_image::<colortype::Gray32>(2, 2, &[1; 4]).expect("u32"));
    assert!(message(&import(&u32s, &opts(1.0, None)).expect_err("u32")).contains("u32 samples"));
    let f64s = tiff_of(&|e| e.write_image::<colortype::Gray64Float>(2, 2, &[1.0; 4]).expect("f64"));
    assert!(message(&import(&f64s, &opts(1.0, None)).expect_err("f64")).contains("u16, i16 or f32"));
}

#[test]
fn truncated_tiffs_are_errors_not_panics() {
    let data: Vec<f32> = (0..64 * 64).map(|k| k as f32).collect();
    let bytes = tiff_f32(64, 64, &data, Some([1.0, 1.0, 0.0]), None);
    for n in [4, 8, 9, 100, bytes.len() / 2, bytes.len() - 1] {
        assert!(import(&bytes[..n], &ImportOptions::default()).is_err(), "{n} bytes");
    }
    for k in (0..bytes.len()).step_by(97).chain(0..16) {
        let mut b = bytes.clone();
        b[k] ^= 0x5A;
        let _ = import(&b, &ImportOptions::default());
    }
}
