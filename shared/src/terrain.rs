//! A scene's terrain (`.cterrain`): a heightfield on a regular grid, cut into square tiles that a
//! client fetches by byte range, only those near its camera (like the instance pack). Byte
//! layout: `docs/scenes.md`, "Terrain".
//!
//! Conventions: y up; ground-plane coordinates `[x, z]` in metres; sample `(i, j)` lies at
//! `origin + (i·cell, j·cell)` (i along x, j along z); heights are stored as u16
//! `height_min + q·height_step` metres. The surface between samples is the grid split into two
//! triangles per cell along the diagonal from `(i, j)` to `(i+1, j+1)`: [`cell_height`] is that
//! surface, the one that instances stand on, the viewer and the evaluation draw, and occlusion
//! culling bounds. A tile of `tile_cells` cells per side holds its edge samples too, so it is
//! drawn and sampled alone.

use crc32fast::hash as crc32;
use serde::{Deserialize, Serialize};

/// File magic.
pub const TERRAIN_MAGIC: [u8; 8] = *b"CNPYTERR";
/// Major version; readers reject others.
pub const TERRAIN_VERSION_MAJOR: u16 = 1;
/// Minor version; readers accept higher ones.
pub const TERRAIN_VERSION_MINOR: u16 = 0;
/// Header length.
pub const TERRAIN_HEADER_LEN: usize = 64;
/// Tile table record length.
pub const TERRAIN_TILE_RECORD_LEN: usize = 32;
/// Cells per tile side written by default.
pub const DEFAULT_TILE_CELLS: u32 = 64;
/// Most samples along one side.
pub const MAX_SIDE_SAMPLES: u32 = 16_385;
/// Most samples in all (a 4097² grid): 64 MiB of f32 decoded.
pub const MAX_SAMPLES: u64 = 4097 * 4097;
/// Most cells per tile side.
pub const MAX_TILE_CELLS: u32 = 1024;

/// The grid a terrain's samples lie on.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TerrainGrid {
    /// Position of sample (0, 0): x, z.
    pub origin: [f64; 2],
    /// Spacing of samples, metres.
    pub cell: f64,
    /// Samples along x and along z (each ≥ 2).
    pub samples: [u32; 2],
    /// Cells per tile side.
    pub tile_cells: u32,
    /// Height of the quantized value 0, metres.
    pub height_min: f32,
    /// Metres per quantized step (> 0).
    pub height_step: f32,
}

/// Why a terrain is refused.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum TerrainError {
    /// Too short, wrong magic, bad version, a length or value that disagrees.
    #[error("not a valid terrain: {0}")]
    Invalid(String),
    /// A CRC disagrees.
    #[error("terrain CRC mismatch in {0}")]
    Crc(String),
    /// Past the sizes a terrain may have.
    #[error("terrain limits exceeded: {0}")]
    Limits(String),
}

fn invalid(s: impl Into<String>) -> TerrainError {
    TerrainError::Invalid(s.into())
}

impl TerrainGrid {
    /// Checks the grid: sizes within the limits, finite positive spacing and step.
    pub fn check(&self) -> Result<(), TerrainError> {
        let [nx, nz] = self.samples;
        if nx < 2 || nz < 2 {
            return Err(invalid(format!("{nx} × {nz} samples: at least 2 × 2")));
        }
        if nx > MAX_SIDE_SAMPLES || nz > MAX_SIDE_SAMPLES || u64::from(nx) * u64::from(nz) > MAX_SAMPLES {
            return Err(TerrainError::Limits(format!(
                "{nx} × {nz} samples (at most {MAX_SIDE_SAMPLES} a side, {MAX_SAMPLES} in all)"
            )));
        }
        if !(1..=MAX_TILE_CELLS).contains(&self.tile_cells) {
            return Err(invalid(format!("{} cells per tile", self.tile_cells)));
        }
        if !(self.cell.is_finite() && self.cell > 0.0 && self.cell <= 10_000.0) {
            return Err(invalid(format!("cell size {}", self.cell)));
        }
        if !self.origin.iter().all(|v| v.is_finite() && v.abs() < 1e7) {
            return Err(invalid(format!("origin {:?}", self.origin)));
        }
        let top = f64::from(self.height_min) + 65_535.0 * f64::from(self.height_step);
        if !(self.height_min.is_finite() && self.height_step.is_finite() && self.height_step > 0.0 && top.abs() < 1e6) {
            return Err(invalid(format!(
                "heights from {} by {}",
                self.height_min, self.height_step
            )));
        }
        Ok(())
    }

    /// Tiles along x and along z.
    pub fn tiles(&self) -> [u32; 2] {
        let n = |s: u32| (s - 1).div_ceil(self.tile_cells);
        [n(self.samples[0]), n(self.samples[1])]
    }

    /// Tile `(tx, tz)`'s first sample and its sample counts along x and z.
    pub fn tile_samples(&self, tx: u32, tz: u32) -> ([u32; 2], [u32; 2]) {
        let c = self.tile_cells;
        let (i0, j0) = (tx * c, tz * c);
        let i1 = (i0 + c).min(self.samples[0] - 1);
        let j1 = (j0 + c).min(self.samples[1] - 1);
        ([i0, j0], [i1 - i0 + 1, j1 - j0 + 1])
    }

    /// Ground rectangle of sample range `i0..=i1`, `j0..=j1`: min x, min z, max x, max z.
    pub fn rect(&self, i0: u32, j0: u32, i1: u32, j1: u32) -> [f32; 4] {
        let x = |i: u32| (self.origin[0] + f64::from(i) * self.cell) as f32;
        let z = |j: u32| (self.origin[1] + f64::from(j) * self.cell) as f32;
        [x(i0), z(j0), x(i1), z(j1)]
    }

    /// The whole grid's rectangle.
    pub fn bounds(&self) -> [f32; 4] {
        self.rect(0, 0, self.samples[0] - 1, self.samples[1] - 1)
    }

    /// The tile holding ground point `(x, z)` (clamped into the grid), and the point's sample
    /// coordinates (fractional, clamped).
    pub fn locate(&self, x: f32, z: f32) -> ([u32; 2], [f64; 2]) {
        let clamp = |v: f32, o: f64, n: u32| ((f64::from(v) - o) / self.cell).clamp(0.0, f64::from(n - 1));
        let u = clamp(x, self.origin[0], self.samples[0]);
        let w = clamp(z, self.origin[1], self.samples[1]);
        let [tx_n, tz_n] = self.tiles();
        let t = |s: f64, n: u32| ((s / f64::from(self.tile_cells)).floor() as u32).min(n - 1);
        ([t(u, tx_n), t(w, tz_n)], [u, w])
    }

    /// Metres of a quantized height.
    pub fn height_of(&self, q: u16) -> f32 {
        self.height_min + f32::from(q) * self.height_step
    }
}

/// Height of the surface inside one cell from its corners (`h00` at `(i, j)`, `h10` at
/// `(i+1, j)`, `h01` at `(i, j+1)`, `h11` at `(i+1, j+1)`) at fractions `fx`, `fz` in [0, 1]:
/// the two triangles split along the `(i, j)`–`(i+1, j+1)` diagonal.
pub fn cell_height(h00: f32, h10: f32, h01: f32, h11: f32, fx: f32, fz: f32) -> f32 {
    if fx >= fz {
        h00 + fx * (h10 - h00) + fz * (h11 - h10)
    } else {
        h00 + fz * (h01 - h00) + fx * (h11 - h01)
    }
}

/// A tile's record (the file's tile table, repeated in the manifest).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TerrainTile {
    /// Tile column (along x).
    pub x: u16,
    /// Tile row (along z).
    pub z: u16,
    /// Absolute offset of its samples.
    pub offset: u64,
    /// Bytes of its samples (2 per sample).
    pub length: u64,
    /// CRC-32 of its samples.
    pub crc32: u32,
    /// Lowest and highest sample, metres.
    pub min_height: f32,
    /// Highest sample, metres.
    pub max_height: f32,
    /// Ground rectangle: min x, min z, max x, max z.
    pub bounds: [f32; 4],
}

/// A tile's samples, decoded: heights in metres, row by row (z), each row along x.
#[derive(Debug, Clone, PartialEq)]
pub struct TileSamples {
    /// First sample (i, j) in the grid.
    pub first: [u32; 2],
    /// Samples along x and z.
    pub size: [u32; 2],
    /// Heights, `size[0] × size[1]`.
    pub heights: Vec<f32>,
}

impl TileSamples {
    /// Height at the grid's sample `(i, j)`, which must lie in the tile.
    pub fn at(&self, i: u32, j: u32) -> f32 {
        let (li, lj) = (i - self.first[0], j - self.first[1]);
        self.heights[(lj * self.size[0] + li) as usize]
    }

    /// The surface height at fractional sample coordinates `(u, w)` inside the tile.
    pub fn height_at(&self, u: f64, w: f64) -> f32 {
        let i = (u.floor() as u32).clamp(self.first[0], self.first[0] + self.size[0] - 2);
        let j = (w.floor() as u32).clamp(self.first[1], self.first[1] + self.size[1] - 2);
        let fx = (u - f64::from(i)).clamp(0.0, 1.0) as f32;
        let fz = (w - f64::from(j)).clamp(0.0, 1.0) as f32;
        cell_height(
            self.at(i, j),
            self.at(i + 1, j),
            self.at(i, j + 1),
            self.at(i + 1, j + 1),
            fx,
            fz,
        )
    }
}

/// Decodes and checks one tile's bytes against its record.
pub fn decode_tile(grid: &TerrainGrid, tile: &TerrainTile, bytes: &[u8]) -> Result<TileSamples, TerrainError> {
    let [tn_x, tn_z] = grid.tiles();
    if u32::from(tile.x) >= tn_x || u32::from(tile.z) >= tn_z {
        return Err(invalid(format!("tile {}/{} outside the grid", tile.x, tile.z)));
    }
    let (first, size) = grid.tile_samples(u32::from(tile.x), u32::from(tile.z));
    let n = (size[0] * size[1]) as usize;
    if bytes.len() != 2 * n || tile.length != 2 * n as u64 {
        return Err(invalid(format!(
            "tile {}/{}: {} bytes for {n} samples",
            tile.x,
            tile.z,
            bytes.len()
        )));
    }
    if crc32(bytes) != tile.crc32 {
        return Err(TerrainError::Crc(format!("tile {}/{}", tile.x, tile.z)));
    }
    let heights = bytes
        .chunks_exact(2)
        .map(|c| grid.height_of(u16::from_le_bytes([c[0], c[1]])))
        .collect();
    Ok(TileSamples { first, size, heights })
}

/// A whole terrain in memory.
#[derive(Debug, Clone, PartialEq)]
pub struct Heightfield {
    /// Its grid (the height quantization as encoded; [`Heightfield::new`] picks it).
    pub grid: TerrainGrid,
    /// Heights in metres, row by row (z), each row along x: as quantized, so that a decoded
    /// file equals its source.
    pub heights: Vec<f32>,
}

impl Heightfield {
    /// A heightfield from heights in metres (row by row along z, each row along x), quantized to
    /// u16 over their range.
    pub fn new(origin: [f64; 2], cell: f64, samples: [u32; 2], heights: &[f32]) -> Result<Self, TerrainError> {
        let mut grid = TerrainGrid {
            origin,
            cell,
            samples,
            tile_cells: DEFAULT_TILE_CELLS,
            height_min: 0.0,
            height_step: 1.0,
        };
        grid.check()?;
        let n = u64::from(samples[0]) * u64::from(samples[1]);
        if heights.len() as u64 != n {
            return Err(invalid(format!(
                "{} heights for {} × {} samples",
                heights.len(),
                samples[0],
                samples[1]
            )));
        }
        if let Some(h) = heights.iter().find(|h| !h.is_finite() || h.abs() > 1e5) {
            return Err(invalid(format!("height {h}")));
        }
        let lo = heights.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = heights.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        grid.height_min = lo;
        grid.height_step = if hi > lo { (hi - lo) / 65_535.0 } else { 1.0 };
        grid.check()?;
        let heights = heights.iter().map(|&h| grid.height_of(quantize(&grid, h))).collect();
        Ok(Self { grid, heights })
    }

    /// Height at sample `(i, j)` (clamped into the grid).
    pub fn at(&self, i: u32, j: u32) -> f32 {
        let i = i.min(self.grid.samples[0] - 1);
        let j = j.min(self.grid.samples[1] - 1);
        self.heights[(j * self.grid.samples[0] + i) as usize]
    }

    /// The surface height under ground point `(x, z)`, clamped to the grid's edge outside it.
    pub fn height_at(&self, x: f32, z: f32) -> f32 {
        let (_, [u, w]) = self.grid.locate(x, z);
        let i = (u.floor() as u32).min(self.grid.samples[0] - 2);
        let j = (w.floor() as u32).min(self.grid.samples[1] - 2);
        let fx = (u - f64::from(i)).clamp(0.0, 1.0) as f32;
        let fz = (w - f64::from(j)).clamp(0.0, 1.0) as f32;
        cell_height(
            self.at(i, j),
            self.at(i + 1, j),
            self.at(i, j + 1),
            self.at(i + 1, j + 1),
            fx,
            fz,
        )
    }

    /// The file: header, tile table, then each tile's samples, tiles row by row.
    pub fn encode(&self) -> Vec<u8> {
        let g = &self.grid;
        let (records, body) = self.layout();
        let count = records.len() as u32;
        let tables_len = TERRAIN_HEADER_LEN + TERRAIN_TILE_RECORD_LEN * records.len();
        let mut table = Vec::with_capacity(TERRAIN_TILE_RECORD_LEN * records.len());
        for t in &records {
            table.extend_from_slice(&t.x.to_le_bytes());
            table.extend_from_slice(&t.z.to_le_bytes());
            table.extend_from_slice(&t.offset.to_le_bytes());
            table.extend_from_slice(&(t.length as u32).to_le_bytes());
            table.extend_from_slice(&t.crc32.to_le_bytes());
            table.extend_from_slice(&t.min_height.to_le_bytes());
            table.extend_from_slice(&t.max_height.to_le_bytes());
            table.extend_from_slice(&[0; 4]);
        }
        let mut out = Vec::with_capacity(tables_len + body.len());
        out.extend_from_slice(&TERRAIN_MAGIC);
        out.extend_from_slice(&TERRAIN_VERSION_MAJOR.to_le_bytes());
        out.extend_from_slice(&TERRAIN_VERSION_MINOR.to_le_bytes());
        out.extend_from_slice(&g.samples[0].to_le_bytes());
        out.extend_from_slice(&g.samples[1].to_le_bytes());
        out.extend_from_slice(&g.tile_cells.to_le_bytes());
        out.extend_from_slice(&g.origin[0].to_le_bytes());
        out.extend_from_slice(&g.origin[1].to_le_bytes());
        out.extend_from_slice(&g.cell.to_le_bytes());
        out.extend_from_slice(&g.height_min.to_le_bytes());
        out.extend_from_slice(&g.height_step.to_le_bytes());
        out.extend_from_slice(&count.to_le_bytes());
        out.extend_from_slice(&crc32(&table).to_le_bytes());
        debug_assert_eq!(out.len(), TERRAIN_HEADER_LEN);
        out.extend_from_slice(&table);
        out.extend_from_slice(&body);
        out
    }

    /// Reads a whole file: header, tables and every tile, each checked.
    pub fn decode(bytes: &[u8]) -> Result<Self, TerrainError> {
        let (grid, tiles) = decode_tables(bytes)?;
        let mut heights = vec![0.0f32; (grid.samples[0] * grid.samples[1]) as usize];
        for t in &tiles {
            let end = t.offset.checked_add(t.length).filter(|&e| e <= bytes.len() as u64);
            let Some(end) = end else {
                return Err(invalid(format!("tile {}/{} past the end of the file", t.x, t.z)));
            };
            let s = decode_tile(&grid, t, &bytes[t.offset as usize..end as usize])?;
            for lj in 0..s.size[1] {
                for li in 0..s.size[0] {
                    let (i, j) = (s.first[0] + li, s.first[1] + lj);
                    heights[(j * grid.samples[0] + i) as usize] = s.heights[(lj * s.size[0] + li) as usize];
                }
            }
        }
        Ok(Self { grid, heights })
    }

    /// The tile table of the encoded file (what a manifest repeats).
    pub fn tiles(&self) -> Vec<TerrainTile> {
        self.layout().0
    }

    /// The tile records, row by row, and the samples they point at (quantized, little-endian),
    /// as the file lays them out after its tables.
    fn layout(&self) -> (Vec<TerrainTile>, Vec<u8>) {
        let g = &self.grid;
        let [tx_n, tz_n] = g.tiles();
        let tables_len = tables_len((tx_n * tz_n) as usize);
        let mut records = Vec::with_capacity((tx_n * tz_n) as usize);
        let mut body = Vec::new();
        for tz in 0..tz_n {
            for tx in 0..tx_n {
                let (first, size) = g.tile_samples(tx, tz);
                let start = body.len();
                let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                for j in first[1]..first[1] + size[1] {
                    for i in first[0]..first[0] + size[0] {
                        let h = self.at(i, j);
                        (lo, hi) = (lo.min(h), hi.max(h));
                        body.extend_from_slice(&quantize(g, h).to_le_bytes());
                    }
                }
                records.push(TerrainTile {
                    x: tx as u16,
                    z: tz as u16,
                    offset: tables_len + start as u64,
                    length: (body.len() - start) as u64,
                    crc32: crc32(&body[start..]),
                    min_height: lo,
                    max_height: hi,
                    bounds: g.rect(first[0], first[1], first[0] + size[0] - 1, first[1] + size[1] - 1),
                });
            }
        }
        (records, body)
    }
}

fn quantize(g: &TerrainGrid, h: f32) -> u16 {
    (((h - g.height_min) / g.height_step).round()).clamp(0.0, 65_535.0) as u16
}

/// Bytes of header and tile table of a terrain of `tiles` tiles.
pub fn tables_len(tiles: usize) -> u64 {
    (TERRAIN_HEADER_LEN + TERRAIN_TILE_RECORD_LEN * tiles) as u64
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
fn f64_at(b: &[u8], o: usize) -> f64 {
    f64::from_bits(u64_at(b, o))
}

/// Reads and checks the header and the tile table (`bytes` may stop after the table): the grid,
/// and the tiles in file order, each inside the file and of its samples' length.
pub fn decode_tables(bytes: &[u8]) -> Result<(TerrainGrid, Vec<TerrainTile>), TerrainError> {
    if bytes.len() < TERRAIN_HEADER_LEN {
        return Err(invalid(format!("{} bytes: shorter than the header", bytes.len())));
    }
    if bytes[..8] != TERRAIN_MAGIC {
        return Err(invalid("wrong magic"));
    }
    let major = u16_at(bytes, 8);
    if major != TERRAIN_VERSION_MAJOR {
        return Err(invalid(format!(
            "version {major}.{} (this reader reads {TERRAIN_VERSION_MAJOR}.x)",
            u16_at(bytes, 10)
        )));
    }
    let grid = TerrainGrid {
        samples: [u32_at(bytes, 12), u32_at(bytes, 16)],
        tile_cells: u32_at(bytes, 20),
        origin: [f64_at(bytes, 24), f64_at(bytes, 32)],
        cell: f64_at(bytes, 40),
        height_min: f32_at(bytes, 48),
        height_step: f32_at(bytes, 52),
    };
    grid.check()?;
    let count = u32_at(bytes, 56);
    let [tx_n, tz_n] = grid.tiles();
    if u64::from(count) != u64::from(tx_n) * u64::from(tz_n) {
        return Err(invalid(format!("{count} tiles for a {tx_n} × {tz_n} tile grid")));
    }
    let tables_len = tables_len(count as usize) as usize;
    if bytes.len() < tables_len {
        return Err(invalid(format!(
            "{} bytes: shorter than the tile table ({tables_len})",
            bytes.len()
        )));
    }
    let table = &bytes[TERRAIN_HEADER_LEN..tables_len];
    if crc32(table) != u32_at(bytes, 60) {
        return Err(TerrainError::Crc("tile table".into()));
    }
    let mut tiles = Vec::with_capacity(count as usize);
    let mut next = tables_len as u64;
    for (k, r) in table.chunks_exact(TERRAIN_TILE_RECORD_LEN).enumerate() {
        let (x, z) = (u16_at(r, 0), u16_at(r, 2));
        let (tx, tz) = (k as u32 % tx_n, k as u32 / tx_n);
        if (u32::from(x), u32::from(z)) != (tx, tz) {
            return Err(invalid(format!("tile record {k} is {x}/{z}, expected {tx}/{tz}")));
        }
        let (first, size) = grid.tile_samples(tx, tz);
        let offset = u64_at(r, 4);
        let length = u64::from(u32_at(r, 12));
        if offset != next || length != 2 * u64::from(size[0] * size[1]) {
            return Err(invalid(format!("tile {x}/{z} at {offset}+{length}, expected {next}")));
        }
        next = offset + length;
        let (min_height, max_height) = (f32_at(r, 20), f32_at(r, 24));
        if !(min_height.is_finite() && max_height.is_finite() && min_height <= max_height) {
            return Err(invalid(format!("tile {x}/{z} heights {min_height}..{max_height}")));
        }
        tiles.push(TerrainTile {
            x,
            z,
            offset,
            length,
            crc32: u32_at(r, 16),
            min_height,
            max_height,
            bounds: grid.rect(first[0], first[1], first[0] + size[0] - 1, first[1] + size[1] - 1),
        });
    }
    Ok((grid, tiles))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hills(nx: u32, nz: u32) -> Heightfield {
        let h: Vec<f32> = (0..nz)
            .flat_map(|j| (0..nx).map(move |i| 30.0 * ((i as f32) * 0.1).sin() * ((j as f32) * 0.07).cos() + 5.0))
            .collect();
        Heightfield::new([-100.0, -50.0], 2.0, [nx, nz], &h).expect("valid")
    }

    #[test]
    fn round_trips_and_tiles_cover_the_grid() {
        let t = hills(150, 70);
        let bytes = t.encode();
        let back = Heightfield::decode(&bytes).expect("decodes");
        assert_eq!(back, t);
        let tiles = t.tiles();
        assert_eq!(decode_tables(&bytes).expect("tables"), (t.grid, tiles.clone()));
        assert_eq!(t.grid.tiles(), [3, 2]);
        assert_eq!(tiles.len(), 6);
        assert_eq!(tiles[0].bounds, [-100.0, -50.0, 28.0, 78.0]);
        assert_eq!(tiles[5].bounds[2..], [198.0, 88.0]);
        // Each tile alone gives the same surface as the whole field.
        let g = t.grid;
        for (x, z) in [
            (-100.0, -50.0),
            (27.9, 77.0),
            (28.0, 78.0),
            (151.3, 60.1),
            (198.0, 88.0),
        ] {
            let (k, [u, w]) = g.locate(x, z);
            let rec = &tiles[(k[1] * 3 + k[0]) as usize];
            let s =
                decode_tile(&g, rec, &bytes[rec.offset as usize..(rec.offset + rec.length) as usize]).expect("tile");
            assert_eq!(s.height_at(u, w), t.height_at(x, z), "at {x}, {z}");
        }
    }

    #[test]
    fn the_surface_is_the_grid_triangles() {
        let t = Heightfield::new([0.0, 0.0], 1.0, [2, 2], &[0.0, 1.0, 2.0, 4.0]).expect("valid");
        let q = |v: f32| (v - t.height_at(0.0, 0.0)).abs();
        assert!(q(0.0) < 1e-3);
        assert!((t.height_at(1.0, 1.0) - 4.0).abs() < 1e-3);
        // On the diagonal: halfway between h00 and h11.
        assert!((t.height_at(0.5, 0.5) - 2.0).abs() < 1e-3);
        // Below the diagonal (fx > fz): the (0,0) (1,0) (1,1) triangle.
        assert!((t.height_at(0.75, 0.25) - (0.75 * 1.0 + 0.25 * 3.0)).abs() < 1e-3);
        // Outside: clamped to the edge.
        assert_eq!(t.height_at(-5.0, -5.0), t.height_at(0.0, 0.0));
    }

    #[test]
    fn rejects_bad_terrains() {
        let t = hills(70, 70);
        let bytes = t.encode();
        assert!(matches!(
            Heightfield::decode(&bytes[..10]),
            Err(TerrainError::Invalid(_))
        ));
        let mut b = bytes.clone();
        b[0] = b'X';
        assert!(Heightfield::decode(&b).is_err());
        let mut b = bytes.clone();
        b[8] = 2;
        assert!(matches!(Heightfield::decode(&b), Err(TerrainError::Invalid(m)) if m.contains("version")));
        let mut b = bytes.clone();
        let last = b.len() - 1;
        b[last] ^= 0xFF;
        assert!(matches!(Heightfield::decode(&b), Err(TerrainError::Crc(_))));
        let mut b = bytes.clone();
        b[TERRAIN_HEADER_LEN + 5] ^= 1;
        assert!(matches!(Heightfield::decode(&b), Err(TerrainError::Crc(_))));
        // Truncated inside the tiles.
        assert!(Heightfield::decode(&bytes[..bytes.len() - 3]).is_err());
        // Samples: sizes, counts, values.
        assert!(Heightfield::new([0.0; 2], 1.0, [1, 5], &[0.0; 5]).is_err());
        assert!(Heightfield::new([0.0; 2], 1.0, [3, 3], &[0.0; 8]).is_err());
        assert!(Heightfield::new([0.0; 2], 1.0, [2, 2], &[0.0, f32::NAN, 0.0, 0.0]).is_err());
        assert!(Heightfield::new([0.0; 2], 0.0, [2, 2], &[0.0; 4]).is_err());
        assert!(matches!(
            Heightfield::new([0.0; 2], 1.0, [20_000, 2], &[]),
            Err(TerrainError::Limits(_))
        ));
        // Every truncation and every flipped header byte is an error or a checked field, never a
        // panic.
        for n in 0..bytes.len().min(400) {
            let _ = Heightfield::decode(&bytes[..n]);
        }
        for k in 0..TERRAIN_HEADER_LEN {
            let mut b = bytes.clone();
            b[k] ^= 0x5A;
            let _ = Heightfield::decode(&b);
        }
    }

    #[test]
    fn a_flat_field_keeps_its_height() {
        let t = Heightfield::new([0.0; 2], 4.0, [3, 3], &[7.5; 9]).expect("valid");
        assert_eq!(t.height_at(3.0, 5.0), 7.5);
        assert_eq!(Heightfield::decode(&t.encode()).expect("decodes"), t);
    }
}
