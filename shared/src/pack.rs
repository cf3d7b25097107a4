//! The instance pack (`.cpack`): a scene version's tree instances, tiled by a quadtree over the
//! scene's bounds so a client fetches only the tiles near its camera, by byte range. Byte layout:
//! `docs/scenes.md`.

use crc32fast::hash as crc32;

/// File magic.
pub const PACK_MAGIC: [u8; 8] = *b"CNPYPACK";
/// Major version; readers reject others.
pub const PACK_VERSION_MAJOR: u16 = 1;
/// Minor version; readers accept higher ones.
pub const PACK_VERSION_MINOR: u16 = 0;
/// Header length.
pub const PACK_HEADER_LEN: usize = 64;
/// Tile table record length.
pub const TILE_RECORD_LEN: usize = 32;
/// Instance record length.
pub const INSTANCE_RECORD_LEN: usize = 28;
/// A tile is split while it holds more instances than this (and the depth allows).
pub const TILE_CAPACITY: usize = 256;
/// Deepest quadtree level (level 0 is the whole scene).
pub const MAX_DEPTH: u8 = 10;

/// One tree instance.
#[derive(Debug, Clone, PartialEq)]
pub struct PackInstance {
    /// Stable instance id within the scene.
    pub id: u32,
    /// Index into the pack's model table.
    pub model: u16,
    /// Position x, y, z in metres (y up; x, z inside the scene bounds).
    pub position: [f32; 3],
    /// Rotation about +y, radians.
    pub rotation: f32,
    /// Uniform scale.
    pub scale: f32,
}

impl PackInstance {
    /// The instance's placement, model → world, and the scale it applies: uniform scale (1 when
    /// the stored one is not a positive finite number), then rotation about +y, then the
    /// position. Streaming, evaluation and the viewer all place trees with it.
    pub fn placement(&self) -> (glam::Mat4, f32) {
        let scale = if self.scale.is_finite() && self.scale > 0.0 {
            self.scale
        } else {
            1.0
        };
        let m = glam::Mat4::from_scale_rotation_translation(
            glam::Vec3::splat(scale),
            glam::Quat::from_rotation_y(self.rotation),
            glam::Vec3::from(self.position),
        );
        (m, scale)
    }
}

/// One tile of the quadtree (a leaf cell that holds instances).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Tile {
    /// Quadtree level (0 = whole scene).
    pub level: u8,
    /// Cell column at that level, along x.
    pub x: u16,
    /// Cell row at that level, along z.
    pub z: u16,
    /// Instances in the tile.
    pub count: u32,
    /// Absolute offset of the tile's records.
    pub offset: u64,
    /// Bytes of the tile's records (`count × 28`).
    pub length: u64,
    /// CRC-32 of the tile's records.
    pub crc32: u32,
    /// Cell bounds: min x, min z, max x, max z.
    pub bounds: [f32; 4],
}

/// A decoded pack.
#[derive(Debug, Clone, PartialEq)]
pub struct Pack {
    /// Scene bounds: min x, min z, max x, max z.
    pub bounds: [f32; 4],
    /// Model names, indexed by [`PackInstance::model`].
    pub models: Vec<String>,
    /// Tiles in file order (Morton order of their cells).
    pub tiles: Vec<Tile>,
    /// Instances, tile by tile.
    pub instances: Vec<PackInstance>,
}

/// Why a pack could not be built or read.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum PackError {
    /// Too short, wrong magic, bad version, or a length that disagrees.
    #[error("not a valid instance pack: {0}")]
    Invalid(&'static str),
    /// A CRC disagrees.
    #[error("instance pack CRC mismatch in {0}")]
    Crc(&'static str),
    /// Too many models or a name too long.
    #[error("instance pack limits exceeded: {0}")]
    Limits(&'static str),
}

/// The cell at `level` with column `x`, row `z`, over `bounds`.
pub fn cell_bounds(bounds: [f32; 4], level: u8, x: u16, z: u16) -> [f32; 4] {
    let n = f64::from(1u32 << level);
    let (w, d) = (
        f64::from(bounds[2]) - f64::from(bounds[0]),
        f64::from(bounds[3]) - f64::from(bounds[1]),
    );
    let fx = |i: f64| (f64::from(bounds[0]) + w * i / n) as f32;
    let fz = |i: f64| (f64::from(bounds[1]) + d * i / n) as f32;
    [
        fx(f64::from(x)),
        fz(f64::from(z)),
        fx(f64::from(x) + 1.0),
        fz(f64::from(z) + 1.0),
    ]
}

/// Cell index along one axis at [`MAX_DEPTH`], clamped into the grid.
fn grid_index(v: f32, lo: f32, hi: f32) -> u32 {
    let n = 1u32 << MAX_DEPTH;
    let t = if hi > lo {
        (f64::from(v) - f64::from(lo)) / (f64::from(hi) - f64::from(lo))
    } else {
        0.0
    };
    ((t * f64::from(n)).floor().max(0.0) as u32).min(n - 1)
}

/// Interleaves x (even bits) and z (odd bits).
fn morton(x: u32, z: u32) -> u64 {
    let spread = |v: u32| {
        let mut v = u64::from(v) & 0xFFFF_FFFF;
        v = (v | (v << 16)) & 0x0000_FFFF_0000_FFFF;
        v = (v | (v << 8)) & 0x00FF_00FF_00FF_00FF;
        v = (v | (v << 4)) & 0x0F0F_0F0F_0F0F_0F0F;
        v = (v | (v << 2)) & 0x3333_3333_3333_3333;
        (v | (v << 1)) & 0x5555_5555_5555_5555
    };
    spread(x) | (spread(z) << 1)
}

/// Key of an instance's deepest cell: the Morton code of its cell at [`MAX_DEPTH`] (x in even
/// bits, z in odd ones). Packs order instances by (key, id).
pub fn cell_key(bounds: [f32; 4], position: [f32; 3]) -> u64 {
    let gx = grid_index(position[0], bounds[0], bounds[2]);
    let gz = grid_index(position[2], bounds[1], bounds[3]);
    morton(gx, gz)
}

/// The keys of the deepest cells inside the cell at `level`, column `x`, row `z`.
pub fn cell_key_range(level: u8, x: u16, z: u16) -> std::ops::Range<u64> {
    let shift = 2 * u32::from(MAX_DEPTH.saturating_sub(level));
    let lo = morton(u32::from(x), u32::from(z)) << shift;
    lo..lo + (1u64 << shift)
}

/// A tile's cell over a run of instances sorted by (key, id): level, column, row and the run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LeafCell {
    /// Quadtree level (0 = whole scene).
    pub level: u8,
    /// Column at that level, along x.
    pub x: u16,
    /// Row at that level, along z.
    pub z: u16,
    /// First instance of the run.
    pub start: usize,
    /// One past the last.
    pub end: usize,
}

/// The tiles' cells of instances whose sorted cell keys are `keys`: a cell becomes a tile when it
/// holds at most [`TILE_CAPACITY`] instances or is at [`MAX_DEPTH`]; empty cells take no tile.
/// Costs a binary search per visited cell, not a pass over the instances.
pub fn leaf_cells(keys: &[u64]) -> Vec<LeafCell> {
    let mut out = Vec::new();
    split(keys, 0, 0, 0, 0, &mut out);
    out
}

/// The model table's bytes (each name as a u16 length and its UTF-8).
pub fn model_table(models: &[String]) -> Result<Vec<u8>, PackError> {
    if models.len() > usize::from(u16::MAX) {
        return Err(PackError::Limits("more than 65535 models"));
    }
    let mut table = Vec::new();
    for m in models {
        let len = u16::try_from(m.len()).map_err(|_| PackError::Limits("model name longer than 65535 bytes"))?;
        table.extend_from_slice(&len.to_le_bytes());
        table.extend_from_slice(m.as_bytes());
    }
    Ok(table)
}

/// Offset of the first tile's records: header, model table, tile table.
pub fn records_start(model_table_len: usize, tile_count: usize) -> usize {
    PACK_HEADER_LEN + model_table_len + tile_count * TILE_RECORD_LEN
}

/// Appends an instance's 28-byte record.
pub fn encode_record(i: &PackInstance, out: &mut Vec<u8>) {
    out.extend_from_slice(&i.id.to_le_bytes());
    for v in i.position {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&i.rotation.to_le_bytes());
    out.extend_from_slice(&i.scale.to_le_bytes());
    out.extend_from_slice(&i.model.to_le_bytes());
    out.extend_from_slice(&[0, 0]);
}

/// The pack's bytes before its first tile's records (header, model table, tile table), for
/// `tiles` whose offsets and CRCs are final and a pack of `pack_len` bytes in all.
pub fn encode_head(
    bounds: [f32; 4],
    model_count: usize,
    model_table: &[u8],
    tiles: &[Tile],
    instance_count: u32,
    pack_len: u64,
) -> Vec<u8> {
    let table_start = PACK_HEADER_LEN + model_table.len();
    let mut out = vec![0u8; records_start(model_table.len(), tiles.len())];
    for (k, t) in tiles.iter().enumerate() {
        let r = &mut out[table_start + k * TILE_RECORD_LEN..table_start + (k + 1) * TILE_RECORD_LEN];
        r[0] = t.level;
        r[4..6].copy_from_slice(&t.x.to_le_bytes());
        r[6..8].copy_from_slice(&t.z.to_le_bytes());
        r[8..12].copy_from_slice(&t.count.to_le_bytes());
        r[16..24].copy_from_slice(&t.offset.to_le_bytes());
        r[24..28].copy_from_slice(&t.crc32.to_le_bytes());
    }
    out[PACK_HEADER_LEN..table_start].copy_from_slice(model_table);
    let mut h = [0u8; PACK_HEADER_LEN];
    h[0..8].copy_from_slice(&PACK_MAGIC);
    h[8..10].copy_from_slice(&PACK_VERSION_MAJOR.to_le_bytes());
    h[10..12].copy_from_slice(&PACK_VERSION_MINOR.to_le_bytes());
    h[12..16].copy_from_slice(&(PACK_HEADER_LEN as u32).to_le_bytes());
    h[16..24].copy_from_slice(&pack_len.to_le_bytes());
    h[24..28].copy_from_slice(&instance_count.to_le_bytes());
    h[28..32].copy_from_slice(&(tiles.len() as u32).to_le_bytes());
    for (k, b) in bounds.iter().enumerate() {
        h[32 + 4 * k..36 + 4 * k].copy_from_slice(&b.to_le_bytes());
    }
    h[48..52].copy_from_slice(&(model_table.len() as u32).to_le_bytes());
    h[52..54].copy_from_slice(&(model_count as u16).to_le_bytes());
    h[54] = MAX_DEPTH;
    h[56..60].copy_from_slice(&crc32(&out[PACK_HEADER_LEN..]).to_le_bytes());
    let hc = crc32(&h[..60]);
    h[60..64].copy_from_slice(&hc.to_le_bytes());
    out[..PACK_HEADER_LEN].copy_from_slice(&h);
    out
}

/// Builds a pack. Instances are sorted into Morton order of their deepest cell (ties by id), then
/// split recursively ([`leaf_cells`]).
pub fn build(
    bounds: [f32; 4],
    models: &[String],
    instances: &[PackInstance],
) -> Result<(Vec<u8>, Vec<Tile>), PackError> {
    let model_table = model_table(models)?;
    let mut keyed: Vec<(u64, &PackInstance)> = instances.iter().map(|i| (cell_key(bounds, i.position), i)).collect();
    keyed.sort_by_key(|(k, i)| (*k, i.id));
    let keys: Vec<u64> = keyed.iter().map(|(k, _)| *k).collect();
    let cells = leaf_cells(&keys);
    let start = records_start(model_table.len(), cells.len());
    let total = start + instances.len() * INSTANCE_RECORD_LEN;
    let mut out = vec![0u8; start];
    out.reserve(total - start);
    let mut tiles = Vec::with_capacity(cells.len());
    for c in &cells {
        let offset = out.len();
        for (_, i) in &keyed[c.start..c.end] {
            encode_record(i, &mut out);
        }
        tiles.push(Tile {
            level: c.level,
            x: c.x,
            z: c.z,
            count: (c.end - c.start) as u32,
            offset: offset as u64,
            length: (out.len() - offset) as u64,
            crc32: crc32(&out[offset..]),
            bounds: cell_bounds(bounds, c.level, c.x, c.z),
        });
    }
    let head = encode_head(
        bounds,
        models.len(),
        &model_table,
        &tiles,
        instances.len() as u32,
        out.len() as u64,
    );
    out[..start].copy_from_slice(&head);
    Ok((out, tiles))
}

fn split(keys: &[u64], base: usize, level: u8, x: u16, z: u16, out: &mut Vec<LeafCell>) {
    if keys.is_empty() {
        return;
    }
    if keys.len() <= TILE_CAPACITY || level == MAX_DEPTH {
        out.push(LeafCell {
            level,
            x,
            z,
            start: base,
            end: base + keys.len(),
        });
        return;
    }
    let shift = 2 * u32::from(MAX_DEPTH - level - 1);
    let mut start = 0;
    for child in 0..4u64 {
        let end = start + keys[start..].partition_point(|k| (k >> shift) & 3 <= child);
        let (cx, cz) = ((child & 1) as u16, (child >> 1) as u16);
        split(&keys[start..end], base + start, level + 1, x * 2 + cx, z * 2 + cz, out);
        start = end;
    }
}

fn u16_at(b: &[u8], o: usize) -> u16 {
    u16::from_le_bytes([b[o], b[o + 1]])
}
fn u32_at(b: &[u8], o: usize) -> u32 {
    u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]])
}
fn f32_at(b: &[u8], o: usize) -> f32 {
    f32::from_bits(u32_at(b, o))
}
fn u64_at(b: &[u8], o: usize) -> u64 {
    u64::from(u32_at(b, o)) | (u64::from(u32_at(b, o + 4)) << 32)
}

/// Decodes one tile's instance records as a client fetched them by range: `bytes` must be the
/// tile's whole record run (a multiple of 28 bytes) whose CRC-32 is `crc` (from the tile table or
/// the manifest); every model index must be below `model_count`.
pub fn decode_tile_records(bytes: &[u8], crc: u32, model_count: usize) -> Result<Vec<PackInstance>, PackError> {
    if !bytes.len().is_multiple_of(INSTANCE_RECORD_LEN) {
        return Err(PackError::Invalid("tile length is not a multiple of the record length"));
    }
    if crc32(bytes) != crc {
        return Err(PackError::Crc("tile records"));
    }
    bytes
        .chunks_exact(INSTANCE_RECORD_LEN)
        .map(|rec| {
            let model = u16_at(rec, 24);
            if usize::from(model) >= model_count {
                return Err(PackError::Invalid("instance names a missing model"));
            }
            Ok(PackInstance {
                id: u32_at(rec, 0),
                position: [f32_at(rec, 4), f32_at(rec, 8), f32_at(rec, 12)],
                rotation: f32_at(rec, 16),
                scale: f32_at(rec, 20),
                model,
            })
        })
        .collect()
}

/// Decodes and checks a whole pack (every CRC, every offset). Never panics on any input.
pub fn decode(b: &[u8]) -> Result<Pack, PackError> {
    if b.len() < PACK_HEADER_LEN {
        return Err(PackError::Invalid("shorter than the header"));
    }
    if b[0..8] != PACK_MAGIC {
        return Err(PackError::Invalid("wrong magic"));
    }
    if crc32(&b[..60]) != u32_at(b, 60) {
        return Err(PackError::Crc("header"));
    }
    if u16_at(b, 8) != PACK_VERSION_MAJOR {
        return Err(PackError::Invalid("unsupported major version"));
    }
    if u32_at(b, 12) as usize != PACK_HEADER_LEN || u64_at(b, 16) != b.len() as u64 {
        return Err(PackError::Invalid("header or file length disagrees"));
    }
    let count = u32_at(b, 24) as usize;
    let tile_count = u32_at(b, 28) as usize;
    let bounds = [f32_at(b, 32), f32_at(b, 36), f32_at(b, 40), f32_at(b, 44)];
    let model_len = u32_at(b, 48) as usize;
    let model_count = usize::from(u16_at(b, 52));
    let table_start = PACK_HEADER_LEN
        .checked_add(model_len)
        .ok_or(PackError::Invalid("model table length"))?;
    let records_start = tile_count
        .checked_mul(TILE_RECORD_LEN)
        .and_then(|t| t.checked_add(table_start))
        .filter(|&e| e <= b.len())
        .ok_or(PackError::Invalid("tables run past the end"))?;
    if crc32(&b[PACK_HEADER_LEN..records_start]) != u32_at(b, 56) {
        return Err(PackError::Crc("model and tile tables"));
    }
    let mut models = Vec::with_capacity(model_count.min(4096));
    let mut o = PACK_HEADER_LEN;
    for _ in 0..model_count {
        if o + 2 > table_start {
            return Err(PackError::Invalid("model table overruns"));
        }
        let n = usize::from(u16_at(b, o));
        let name = b
            .get(o + 2..o + 2 + n)
            .filter(|_| o + 2 + n <= table_start)
            .ok_or(PackError::Invalid("model table overruns"))?;
        models.push(String::from_utf8(name.to_vec()).map_err(|_| PackError::Invalid("model name is not UTF-8"))?);
        o += 2 + n;
    }
    if o != table_start {
        return Err(PackError::Invalid("model table length disagrees"));
    }
    let mut tiles = Vec::with_capacity(tile_count.min(1 << 16));
    let mut instances = Vec::with_capacity(count.min(1 << 20));
    let mut expect = records_start;
    for k in 0..tile_count {
        let r = &b[table_start + k * TILE_RECORD_LEN..table_start + (k + 1) * TILE_RECORD_LEN];
        let t_count = u32_at(r, 8);
        let offset = u64_at(r, 16);
        let length = u64::from(t_count) * INSTANCE_RECORD_LEN as u64;
        if offset != expect as u64 || offset + length > b.len() as u64 || r[0] > MAX_DEPTH {
            return Err(PackError::Invalid("tile offsets are not contiguous"));
        }
        let recs = &b[offset as usize..(offset + length) as usize];
        instances.extend(decode_tile_records(recs, u32_at(r, 24), models.len())?);
        let (level, x, z) = (r[0], u16_at(r, 4), u16_at(r, 6));
        tiles.push(Tile {
            level,
            x,
            z,
            count: t_count,
            offset,
            length,
            crc32: u32_at(r, 24),
            bounds: cell_bounds(bounds, level, x, z),
        });
        expect = (offset + length) as usize;
    }
    if expect != b.len() || instances.len() != count {
        return Err(PackError::Invalid("instance count or trailing bytes disagree"));
    }
    Ok(Pack {
        bounds,
        models,
        tiles,
        instances,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn inst(id: u32, x: f32, z: f32) -> PackInstance {
        PackInstance {
            id,
            model: (id % 2) as u16,
            position: [x, 1.0, z],
            rotation: 0.5,
            scale: 1.1,
        }
    }

    #[test]
    fn tiles_cover_their_instances_and_round_trip() {
        let bounds = [-500.0, -400.0, 500.0, 600.0];
        let mut v = Vec::new();
        let mut s = 12345u64;
        for id in 0..3000 {
            s = s
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let x = -500.0 + ((s >> 33) % 1000) as f32;
            let z = -400.0 + ((s >> 13) % 1000) as f32;
            v.push(inst(id, x, z));
        }
        let models = vec!["oak".to_string(), "birch".to_string()];
        let (bytes, tiles) = build(bounds, &models, &v).expect("build");
        assert!(tiles.len() > 1);
        let p = decode(&bytes).expect("decode");
        assert_eq!(p.tiles, tiles);
        assert_eq!(p.instances.len(), v.len());
        for t in &p.tiles {
            assert!(t.count as usize <= TILE_CAPACITY);
            let recs = &bytes[t.offset as usize..(t.offset + t.length) as usize];
            for rec in recs.chunks_exact(INSTANCE_RECORD_LEN) {
                let (x, z) = (f32_at(rec, 4), f32_at(rec, 12));
                assert!(
                    x >= t.bounds[0] - 1e-3
                        && x <= t.bounds[2] + 1e-3
                        && z >= t.bounds[1] - 1e-3
                        && z <= t.bounds[3] + 1e-3
                );
            }
        }
        let mut ids: Vec<u32> = p.instances.iter().map(|i| i.id).collect();
        ids.sort_unstable();
        assert_eq!(ids, (0..3000).collect::<Vec<_>>());
        // Any flipped byte in the tables or records is caught.
        let mut bad = bytes.clone();
        let last = bad.len() - 3;
        bad[last] ^= 1;
        assert_eq!(decode(&bad), Err(PackError::Crc("tile records")));
    }

    #[test]
    fn empty_pack() {
        let (bytes, tiles) = build([0.0, 0.0, 1.0, 1.0], &[], &[]).expect("build");
        assert!(tiles.is_empty());
        assert_eq!(bytes.len(), PACK_HEADER_LEN);
        assert_eq!(decode(&bytes).expect("decode").instances, vec![]);
    }

    proptest! {
        #[test]
        fn decode_never_panics(b in prop::collection::vec(any::<u8>(), 0..400)) {
            let _ = decode(&b);
        }

        #[test]
        fn truncations_are_rejected(n in 0usize..2000) {
            let v: Vec<_> = (0..40).map(|i| inst(i, i as f32, 2.0 * i as f32)).collect();
            let (bytes, _) = build([0.0, 0.0, 100.0, 100.0], &["a".into(), "b".into()], &v).expect("build");
            let cut = n % bytes.len();
            prop_assert!(decode(&bytes[..cut]).is_err());
        }
    }
}
