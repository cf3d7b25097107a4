//! Round trips, the client's fetch sequence, one test per kind of bad input, and every prefix
//! and bit flip of a valid section rejected without a panic.
#![allow(clippy::unwrap_used)]

use glam::Vec3;

use super::*;
use crate::format::{FormatError, crc32};

fn quad(z: f32, size: f32) -> CloudQuad {
    CloudQuad {
        normal: Vec3::Z,
        d: z,
        origin: Vec3::new(-size / 2.0, 0.0, z),
        edge_u: Vec3::X * size,
        edge_v: Vec3::Y * size,
    }
}

fn png(w: u32, h: u32, seed: u8) -> Vec<u8> {
    let img = image::RgbaImage::from_fn(w, h, |x, y| {
        image::Rgba([seed, x as u8, y as u8, 255 * ((x + y) % 2) as u8])
    });
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

fn sample() -> (CloudHeader, Vec<LevelTextures>) {
    let header = CloudHeader {
        center: Vec3::new(0.0, 2.0, 0.0),
        radius: 3.0,
        texture_density: true,
        view_line_height: Some(20.0),
    };
    let levels = vec![
        LevelTextures {
            epsilon: 0.3,
            texel: 0.05,
            planes: (0..3)
                .map(|i| PlaneTexture {
                    quad: quad(i as f32 - 1.0, 2.0),
                    width: 4 + i,
                    height: 3,
                    bytes: png(u32::from(4 + i), 3, i as u8),
                })
                .collect(),
        },
        LevelTextures {
            epsilon: 0.6,
            texel: 0.1,
            planes: vec![PlaneTexture {
                quad: quad(0.0, 4.0),
                width: 2,
                height: 2,
                bytes: png(2, 2, 9),
            }],
        },
    ];
    (header, levels)
}

#[test]
fn round_trip_and_client_fetch() {
    let (header, levels) = sample();
    let bytes = encode_clouds(&header, &levels).unwrap();
    // A client: 4 bytes, then the table, then one level by one range.
    let tl = CloudTable::peek_table_len(&bytes[..4]).unwrap() as usize;
    assert_eq!(tl, CloudTable::table_len(2, 4));
    let t = CloudTable::decode(&bytes[..tl], bytes.len() as u64).unwrap();
    assert_eq!(t.flags, CLOUD_FLAG_TEXTURE_DENSITY | CLOUD_FLAG_VIEW_LINE);
    assert_eq!(t.view_line_height, 20.0);
    assert_eq!(t.levels.len(), 2);
    assert_eq!(t.level_planes(0).len(), 3);
    assert_eq!(t.level_planes(1)[0].quad, levels[1].planes[0].quad);
    let r = t.level_range(0).unwrap();
    let imgs = t.decode_level(0, &bytes[r.start as usize..r.end as usize]).unwrap();
    assert_eq!(imgs.len(), 3);
    assert_eq!((imgs[2].width(), imgs[2].height()), (6, 3));
    assert_eq!(imgs[1].get_pixel(2, 1).0, [1, 2, 1, 255]);
    // A client checks a fetched level's CRCs before caching it: one flipped byte in any
    // plane's texture, or a short body, is rejected.
    let mut level = bytes[r.start as usize..r.end as usize].to_vec();
    t.verify_level(0, &level).unwrap();
    assert!(matches!(
        t.verify_level(0, &level[1..]),
        Err(FormatError::Truncated { .. })
    ));
    let last = level.len() - 1;
    level[last] ^= 1;
    assert!(matches!(
        t.verify_level(0, &level),
        Err(FormatError::ChecksumMismatch { .. })
    ));
    assert!(matches!(t.verify_level(9, &level), Err(FormatError::CloudCounts(_))));
    // One plane alone, by its own range.
    let p = t.planes[3];
    let r = p.texture.range();
    let img = CloudTable::decode_texture(&p, &bytes[r.start as usize..r.end as usize]).unwrap();
    assert_eq!(img.width(), 2);
    assert_eq!(decode_clouds(&bytes).unwrap(), t);
    // Levels switch farther out as ε grows.
    let d0 = t.levels[0].switch_distance(1.0, 1080.0, 1.0);
    assert!(t.levels[1].switch_distance(1.0, 1080.0, 1.0) > d0 && d0 > 0.0);
    assert_eq!(t.planes[0].quad.corners()[2], Vec3::new(1.0, 2.0, -1.0));
}

#[test]
fn empty_section_is_not_baked() {
    let (header, _) = sample();
    assert!(encode_clouds(&header, &[]).unwrap().is_empty());
    let t = decode_clouds(&[]).unwrap();
    assert!(t.levels.is_empty() && t.planes.is_empty());
    assert_eq!(t.level_range(0), None);
    assert!(t.level_planes(0).is_empty());
}

/// Rewrites a table field and fixes the table CRC, so the check under test is the one that
/// fires (not the CRC).
fn patch(bytes: &[u8], at: usize, v: &[u8]) -> Vec<u8> {
    let mut b = bytes.to_vec();
    b[at..at + v.len()].copy_from_slice(v);
    let tl = CloudTable::peek_table_len(&b).unwrap() as usize;
    let crc = crc32(&b[..tl - 4]);
    b[tl - 4..tl].copy_from_slice(&crc.to_le_bytes());
    b
}

fn plane_at(level_count: usize, i: usize) -> usize {
    CLOUD_HEADER_LEN + CLOUD_LEVEL_ENTRY_LEN * level_count + CLOUD_PLANE_RECORD_LEN * i
}

#[test]
fn each_kind_of_bad_input_gives_its_error() {
    let (header, levels) = sample();
    let bytes = encode_clouds(&header, &levels).unwrap();
    let n = bytes.len() as u64;
    let dec = |b: &[u8]| CloudTable::decode(b, b.len() as u64);
    // Truncated: a prefix shorter than the table.
    assert!(matches!(
        CloudTable::decode(&bytes[..40], n),
        Err(FormatError::Truncated { .. })
    ));
    assert!(matches!(
        CloudTable::decode(&bytes[..2], n),
        Err(FormatError::Truncated { .. })
    ));
    // Table length larger than the section, or disagreeing with the counts.
    assert!(matches!(
        CloudTable::decode(&bytes, 50),
        Err(FormatError::CloudTableLength { .. })
    ));
    let b = patch(&bytes, 8, &5u32.to_le_bytes());
    assert!(matches!(dec(&b), Err(FormatError::CloudTableLength { .. })));
    // Bad counts: a level that claims more planes than there are.
    let b = patch(&bytes, CLOUD_HEADER_LEN + 4, &9u32.to_le_bytes());
    assert!(matches!(dec(&b), Err(FormatError::CloudCounts(_))), "{:?}", dec(&b));
    let b = patch(&bytes, CLOUD_HEADER_LEN + 4, &0u32.to_le_bytes());
    assert!(matches!(dec(&b), Err(FormatError::CloudCounts(_))));
    // Bad CRC of the table.
    let mut b = bytes.clone();
    b[13] ^= 0x40;
    assert!(matches!(
        dec(&b),
        Err(FormatError::ChecksumMismatch {
            what: "cloud table",
            ..
        })
    ));
    // Texture offsets: out of range, overlapping, leaving a gap.
    let off = plane_at(2, 1) + 56;
    let first = u32::from_le_bytes(bytes[off..off + 4].try_into().unwrap());
    let b = patch(&bytes, off, &(n as u32 + 5).to_le_bytes());
    assert!(matches!(dec(&b), Err(FormatError::TextureOutOfRange { plane: 1, .. })));
    let b = patch(&bytes, off, &(first - 1).to_le_bytes());
    assert!(matches!(dec(&b), Err(FormatError::TextureOverlap { plane: 1, .. })));
    let b = patch(&bytes, off, &(first + 1).to_le_bytes());
    assert!(matches!(dec(&b), Err(FormatError::TextureGap { plane: 1, .. })));
    let b = patch(&bytes, plane_at(2, 0) + 56, &8u32.to_le_bytes());
    assert!(matches!(dec(&b), Err(FormatError::TextureOverlap { plane: 0, .. })));
    // Trailing bytes after the last texture.
    let mut b = bytes.clone();
    b.push(0);
    assert!(matches!(
        dec(&b),
        Err(FormatError::TrailingBytes {
            what: "billboard-cloud section",
            extra: 1
        })
    ));
    // A level range that disagrees with its planes.
    let b = patch(&bytes, CLOUD_HEADER_LEN + 20, &1u32.to_le_bytes());
    assert!(matches!(dec(&b), Err(FormatError::CloudCounts(_))));
    // Geometry: a non-unit normal, a NaN, a plane offset that disagrees with the corner.
    let b = patch(&bytes, plane_at(2, 2), &2f32.to_le_bytes());
    assert!(matches!(
        dec(&b),
        Err(FormatError::Invalid {
            what: "cloud plane",
            ..
        })
    ));
    let b = patch(&bytes, plane_at(2, 2) + 20, &f32::NAN.to_le_bytes());
    assert!(matches!(
        dec(&b),
        Err(FormatError::Invalid {
            what: "cloud plane",
            ..
        })
    ));
    let b = patch(&bytes, plane_at(2, 2) + 12, &7f32.to_le_bytes());
    assert!(matches!(
        dec(&b),
        Err(FormatError::Invalid {
            what: "cloud plane",
            ..
        })
    ));
    // Unknown codec and flag bits; ε not increasing.
    let b = patch(&bytes, 4, &[3]);
    assert!(matches!(
        dec(&b),
        Err(FormatError::Invalid {
            what: "cloud codec",
            ..
        })
    ));
    let b = patch(&bytes, 6, &8u16.to_le_bytes());
    assert!(matches!(
        dec(&b),
        Err(FormatError::Invalid {
            what: "cloud flags",
            ..
        })
    ));
    let b = patch(
        &bytes,
        CLOUD_HEADER_LEN + CLOUD_LEVEL_ENTRY_LEN + 8,
        &0.1f32.to_le_bytes(),
    );
    assert!(matches!(
        dec(&b),
        Err(FormatError::Invalid {
            what: "cloud level",
            ..
        })
    ));
    // Texture bytes: a flipped bit fails that plane's CRC only; a short fetch is truncated.
    let t = dec(&bytes).unwrap();
    let mut b = bytes.clone();
    let last = b.len() - 1;
    b[last] ^= 1;
    assert!(matches!(
        t.texture_bytes(&b, 3),
        Err(FormatError::ChecksumMismatch {
            what: "cloud texture",
            ..
        })
    ));
    assert!(t.texture_bytes(&b, 0).is_ok());
    assert!(matches!(decode_clouds(&b), Err(FormatError::ChecksumMismatch { .. })));
    let p = t.planes[3];
    let r = p.texture.range();
    assert!(matches!(
        CloudTable::verify_texture(&p, &bytes[r.start as usize..r.end as usize - 1]),
        Err(FormatError::Truncated { .. })
    ));
    // A PNG whose size disagrees with the record (CRC fixed so the size check fires).
    let mut q = p;
    q.width = 3;
    assert!(matches!(
        CloudTable::decode_texture(&q, &bytes[r.start as usize..r.end as usize]),
        Err(FormatError::CloudImage(_))
    ));
}

#[test]
fn every_prefix_and_bit_flip_is_rejected_without_panic() {
    let (header, levels) = sample();
    let bytes = encode_clouds(&header, &levels).unwrap();
    for n in 1..bytes.len() {
        assert!(decode_clouds(&bytes[..n]).is_err(), "prefix {n}");
    }
    for i in 0..bytes.len() {
        for bit in [0u8, 5, 7] {
            let mut b = bytes.clone();
            b[i] ^= 1 << bit;
            assert!(decode_clouds(&b).is_err(), "flip at {i}");
        }
    }
}

#[test]
fn encoder_rejects_what_the_decoder_would() {
    let (header, levels) = sample();
    let mut l = levels.clone();
    l[1].epsilon = 0.2;
    assert!(encode_clouds(&header, &l).is_err());
    let mut l = levels.clone();
    l[0].planes[0].quad.normal = Vec3::X;
    assert!(encode_clouds(&header, &l).is_err());
    let mut l = levels.clone();
    l[1].planes.clear();
    assert!(encode_clouds(&header, &l).is_err());
    let mut l = levels.clone();
    l[0].planes[1].width = 0;
    assert!(encode_clouds(&header, &l).is_err());
    let h = CloudHeader { radius: 0.0, ..header };
    assert!(encode_clouds(&h, &levels).is_err());
    let h = CloudHeader {
        view_line_height: Some(0.0),
        ..header
    };
    assert!(encode_clouds(&h, &levels).is_err());
}
