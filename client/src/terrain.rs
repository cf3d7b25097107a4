//! A scene's terrain on the client: the tiles held so far (fetched by range, nearest first, each
//! checked), the ground's height where known, a lower bound of it over any rectangle for
//! occlusion culling ([`crate::lod::occlusion`]), and the meshes the viewer and the evaluation
//! draw.
//!
//! Conventions: as [`canopy_shared::terrain`] (y up, metres, the grid's two triangles per
//! cell). A tile not yet held is known only by its record in the manifest: its lowest and
//! highest sample, which bound it.

use canopy_shared::manifest::ManifestTerrain;
use canopy_shared::terrain::{Heightfield, TerrainError, TerrainGrid, TerrainTile, TileSamples, decode_tile};
use glam::Vec3;

use crate::lod::occlusion::LowerBound;
use crate::net::{ByteRange, RangeSource};

/// Cells per side of the lower-bound pyramid's finest block.
const BLOCK_CELLS: u32 = 4;

/// The terrain tiles a client holds.
#[derive(Debug, Clone)]
pub struct HeldTerrain {
    /// The grid.
    pub grid: TerrainGrid,
    /// The tiles' records, row by row.
    pub records: Vec<TerrainTile>,
    /// The held tiles' samples (same order).
    tiles: Vec<Option<TileSamples>>,
    /// Lowest ground per block, finest level first (`levels[k]` has blocks of
    /// `BLOCK_CELLS·2^k` cells): from held samples, or the tile's record where not held.
    levels: Vec<(u32, u32, Vec<f32>)>,
    highest: f32,
    /// Bumped whenever a tile arrives (the viewer re-uploads its meshes).
    pub generation: u64,
}

impl HeldTerrain {
    /// Nothing held yet, from the manifest's terrain.
    pub fn new(t: &ManifestTerrain) -> Self {
        let highest = t.tiles.iter().map(|r| r.max_height).fold(f32::NEG_INFINITY, f32::max);
        let mut held = Self {
            grid: t.grid,
            records: t.tiles.clone(),
            tiles: vec![None; t.tiles.len()],
            levels: Vec::new(),
            highest,
            generation: 0,
        };
        held.rebuild();
        held
    }

    /// Everything held, from a whole terrain (the evaluation's reference, paths).
    pub fn from_heightfield(h: &Heightfield) -> Self {
        let records = h.tiles();
        let [nx, _] = h.grid.tiles();
        let tiles = records
            .iter()
            .enumerate()
            .map(|(k, _)| {
                let (first, size) = h.grid.tile_samples(k as u32 % nx, k as u32 / nx);
                let heights = (0..size[1])
                    .flat_map(|j| (0..size[0]).map(move |i| (i, j)))
                    .map(|(i, j)| h.at(first[0] + i, first[1] + j))
                    .collect();
                Some(TileSamples { first, size, heights })
            })
            .collect();
        let highest = h.heights.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        let mut held = Self {
            grid: h.grid,
            records,
            tiles,
            levels: Vec::new(),
            highest,
            generation: 1,
        };
        held.rebuild();
        held
    }

    /// Tiles held.
    pub fn held(&self) -> usize {
        self.tiles.iter().filter(|t| t.is_some()).count()
    }

    /// The held tiles: record index and samples.
    pub fn held_tiles(&self) -> impl Iterator<Item = (usize, &TileSamples)> {
        self.tiles
            .iter()
            .enumerate()
            .filter_map(|(k, t)| Some((k, t.as_ref()?)))
    }

    /// Tiles within `radius` of `(x, z)` neither held nor in `in_flight`, nearest first, and
    /// their byte ranges.
    pub fn tiles_to_load(&self, eye: Vec3, radius: f32, in_flight: &[usize]) -> (Vec<usize>, Vec<ByteRange>) {
        let mut want: Vec<(f32, usize)> = self
            .records
            .iter()
            .enumerate()
            .filter(|(k, _)| self.tiles[*k].is_none() && !in_flight.contains(k))
            .filter_map(|(k, r)| {
                let b = r.bounds;
                let dx = (b[0] - eye.x).max(0.0).max(eye.x - b[2]);
                let dz = (b[1] - eye.z).max(0.0).max(eye.z - b[3]);
                let d = (dx * dx + dz * dz).sqrt();
                (d <= radius).then_some((d, k))
            })
            .collect();
        want.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let tiles: Vec<usize> = want.into_iter().map(|(_, k)| k).collect();
        let ranges = tiles
            .iter()
            .map(|&k| self.records[k].offset..self.records[k].offset + self.records[k].length)
            .collect();
        (tiles, ranges)
    }

    /// Takes in fetched tiles (bodies in the order of `tiles`); returns how many failed their
    /// check (they are asked for again).
    pub fn receive(&mut self, tiles: &[usize], bodies: &[bytes::Bytes]) -> u64 {
        let mut bad = 0;
        for (&k, body) in tiles.iter().zip(bodies) {
            let Some(rec) = self.records.get(k) else {
                continue;
            };
            match decode_tile(&self.grid, rec, body) {
                Ok(s) => self.tiles[k] = Some(s),
                Err(_) => bad += 1,
            }
        }
        self.generation += 1;
        self.rebuild();
        bad
    }

    fn tile_index(&self, tx: u32, tz: u32) -> usize {
        (tz * self.grid.tiles()[0] + tx) as usize
    }

    /// The ground's height at `(x, z)` where its tile is held; `None` outside the grid or where
    /// not held.
    pub fn height_at(&self, x: f32, z: f32) -> Option<f32> {
        if !self.inside(x, z) {
            return None;
        }
        let ([tx, tz], [u, w]) = self.grid.locate(x, z);
        self.tiles[self.tile_index(tx, tz)].as_ref().map(|s| s.height_at(u, w))
    }

    /// A height the ground under `(x, z)` is known not to exceed: the held height, else the
    /// tile record's highest sample; `None` outside the grid.
    pub fn ceiling_at(&self, x: f32, z: f32) -> Option<f32> {
        if !self.inside(x, z) {
            return None;
        }
        self.height_at(x, z).or_else(|| {
            let ([tx, tz], _) = self.grid.locate(x, z);
            Some(self.records[self.tile_index(tx, tz)].max_height)
        })
    }

    fn inside(&self, x: f32, z: f32) -> bool {
        let b = self.grid.bounds();
        x >= b[0] && x <= b[2] && z >= b[1] && z <= b[3]
    }

    /// Rebuilds the lower-bound pyramid from what is held.
    fn rebuild(&mut self) {
        let [cx, cz] = [self.grid.samples[0] - 1, self.grid.samples[1] - 1];
        let (bx, bz) = (cx.div_ceil(BLOCK_CELLS), cz.div_ceil(BLOCK_CELLS));
        let tc = self.grid.tile_cells;
        let [tn_x, _] = self.grid.tiles();
        let mut base = vec![f32::INFINITY; (bx * bz) as usize];
        for j in 0..bz {
            for i in 0..bx {
                // Samples of the block's cells, edges included.
                let (i0, j0) = (i * BLOCK_CELLS, j * BLOCK_CELLS);
                let (i1, j1) = ((i0 + BLOCK_CELLS).min(cx), (j0 + BLOCK_CELLS).min(cz));
                let mut lo = f32::INFINITY;
                for sj in j0..=j1 {
                    for si in i0..=i1 {
                        // A sample on a tile edge lies in both tiles: either gives it.
                        let (tx, tz) = ((si / tc).min(tn_x - 1), (sj / tc).min(self.grid.tiles()[1] - 1));
                        let k = (tz * tn_x + tx) as usize;
                        let a = match &self.tiles[k] {
                            Some(s) => s.at(si, sj),
                            None => self.records[k].min_height,
                        };
                        lo = lo.min(a);
                    }
                }
                base[(j * bx + i) as usize] = lo;
            }
        }
        self.levels = pyramid(bx, bz, base, f32::INFINITY, f32::min);
    }

    /// The pyramid level whose blocks cover rectangle `r` in at most 2 × 2 blocks, and the
    /// rectangle's cell range; `None` when `r` is not inside the grid.
    fn query(&self, r: [f32; 4]) -> Option<(usize, [u32; 4])> {
        let b = self.grid.bounds();
        if !(r[0] >= b[0] && r[1] >= b[1] && r[2] <= b[2] && r[3] <= b[3]) {
            return None;
        }
        let cell = self.grid.cell;
        let (ox, oz) = (self.grid.origin[0], self.grid.origin[1]);
        let [cx, cz] = [self.grid.samples[0] - 1, self.grid.samples[1] - 1];
        let c = |v: f32, o: f64, n: u32| (((f64::from(v) - o) / cell).floor().max(0.0) as u32).min(n - 1);
        let (i0, i1, j0, j1) = (c(r[0], ox, cx), c(r[2], ox, cx), c(r[1], oz, cz), c(r[3], oz, cz));
        let span = (i1 - i0).max(j1 - j0) + 1;
        let mut k = 0usize;
        while k + 1 < self.levels.len() && (BLOCK_CELLS << k) < span {
            k += 1;
        }
        Some((k, [i0, i1, j0, j1]))
    }
}

/// Levels of blocks, each the `fold` of 2 × 2 blocks of the one before, up to a single block.
fn pyramid(w: u32, h: u32, base: Vec<f32>, empty: f32, fold: fn(f32, f32) -> f32) -> Vec<(u32, u32, Vec<f32>)> {
    let mut levels = vec![(w, h, base)];
    while let Some((w, h, prev)) = levels.last().filter(|(w, h, _)| *w > 1 || *h > 1) {
        let (nw, nh) = (w.div_ceil(2), h.div_ceil(2));
        let mut next = vec![empty; (nw * nh) as usize];
        for j in 0..*h {
            for i in 0..*w {
                let slot = &mut next[((j / 2) * nw + i / 2) as usize];
                *slot = fold(*slot, prev[(j * w + i) as usize]);
            }
        }
        levels.push((nw, nh, next));
    }
    levels
}

/// The fold of the blocks of `levels[k]` covering cells `[i0, i1] × [j0, j1]`.
fn fold_blocks(levels: &[(u32, u32, Vec<f32>)], k: usize, c: [u32; 4], init: f32, fold: fn(f32, f32) -> f32) -> f32 {
    let (w, _, v) = &levels[k];
    let size = BLOCK_CELLS << k;
    let mut acc = init;
    for bj in c[2] / size..=c[3] / size {
        for bi in c[0] / size..=c[1] / size {
            acc = fold(acc, v.get((bj * w + bi) as usize).copied().unwrap_or(f32::NEG_INFINITY));
        }
    }
    acc
}

impl LowerBound for HeldTerrain {
    fn lowest_in(&self, r: [f32; 4]) -> f32 {
        match self.query(r) {
            Some((k, c)) => fold_blocks(&self.levels, k, c, f32::INFINITY, f32::min),
            None => f32::NEG_INFINITY,
        }
    }

    fn highest(&self) -> f32 {
        self.highest
    }

    fn extent(&self) -> Option<[f32; 4]> {
        Some(self.grid.bounds())
    }
}

/// A tile's surface as triangles: positions, normals and indices, the grid's diagonal, faces up
/// (counter-clockwise seen from above).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TileMesh {
    /// World positions.
    pub positions: Vec<Vec3>,
    /// Unit normals.
    pub normals: Vec<Vec3>,
    /// Three per triangle.
    pub indices: Vec<u32>,
}

/// The mesh of one tile's samples.
pub fn tile_mesh(grid: &TerrainGrid, s: &TileSamples) -> TileMesh {
    let [w, h] = s.size;
    let cell = grid.cell as f32;
    let mut m = TileMesh::default();
    for lj in 0..h {
        for li in 0..w {
            let (i, j) = (s.first[0] + li, s.first[1] + lj);
            let x = (grid.origin[0] + f64::from(i) * grid.cell) as f32;
            let z = (grid.origin[1] + f64::from(j) * grid.cell) as f32;
            m.positions.push(Vec3::new(x, s.at(i, j), z));
            // Central differences inside the tile, one-sided at its edges.
            let (ia, ib) = (li.saturating_sub(1), (li + 1).min(w - 1));
            let (ja, jb) = (lj.saturating_sub(1), (lj + 1).min(h - 1));
            let at = |a: u32, b: u32| s.at(s.first[0] + a, s.first[1] + b);
            let dx = (at(ib, lj) - at(ia, lj)) / (cell * (ib - ia).max(1) as f32);
            let dz = (at(li, jb) - at(li, ja)) / (cell * (jb - ja).max(1) as f32);
            m.normals.push(Vec3::new(-dx, 1.0, -dz).normalize());
        }
    }
    for lj in 0..h - 1 {
        for li in 0..w - 1 {
            let v = |a: u32, b: u32| b * w + a;
            let (v00, v10, v01, v11) = (v(li, lj), v(li + 1, lj), v(li, lj + 1), v(li + 1, lj + 1));
            m.indices.extend([v00, v11, v10, v00, v01, v11]);
        }
    }
    m
}

/// Why a whole terrain could not be had.
#[derive(Debug, thiserror::Error)]
pub enum FetchTerrainError {
    /// The transfer failed.
    #[error(transparent)]
    Net(#[from] crate::net::NetError),
    /// The file is not a valid terrain.
    #[error("terrain {url}: {source}")]
    Terrain {
        /// Its URL.
        url: String,
        /// Why.
        source: TerrainError,
    },
}

/// Fetches and decodes a scene's whole terrain (what a headless run's camera path flies over).
pub async fn fetch_whole<S: RangeSource>(src: &S, t: &ManifestTerrain) -> Result<Heightfield, FetchTerrainError> {
    let bytes = src.get(&t.url).await?;
    Heightfield::decode(&bytes).map_err(|source| FetchTerrainError::Terrain {
        url: t.url.clone(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field() -> Heightfield {
        let (nx, nz) = (150u32, 90u32);
        let h: Vec<f32> = (0..nx * nz)
            .map(|k| {
                let (i, j) = ((k % nx) as f32, (k / nx) as f32);
                20.0 * (i * 0.11).sin() + 15.0 * (j * 0.07).cos()
            })
            .collect();
        Heightfield::new([-300.0, -180.0], 4.0, [nx, nz], &h).expect("valid")
    }

    fn manifest_terrain(h: &Heightfield) -> ManifestTerrain {
        ManifestTerrain {
            url: "/assets/t.cterrain".into(),
            sha256: String::new(),
            size: h.encode().len() as u64,
            grid: h.grid,
            tiles: h.tiles(),
        }
    }

    #[test]
    fn tiles_arrive_and_bound_the_ground() {
        let h = field();
        let bytes = bytes::Bytes::from(h.encode());
        let mut held = HeldTerrain::new(&manifest_terrain(&h));
        assert_eq!(held.height_at(0.0, 0.0), None);
        // Before any tile: the records bound the ground.
        assert!(held.ceiling_at(0.0, 0.0).expect("inside") >= h.height_at(0.0, 0.0));
        let (tiles, ranges) = held.tiles_to_load(Vec3::new(-290.0, 50.0, -170.0), 1e4, &[]);
        assert_eq!(tiles.len(), held.records.len());
        assert_eq!(tiles[0], 0, "the nearest tile first");
        let (tiles, ranges): (Vec<usize>, Vec<ByteRange>) = tiles.into_iter().zip(ranges).take(2).unzip();
        let bodies: Vec<bytes::Bytes> = ranges
            .iter()
            .map(|r| bytes.slice(r.start as usize..r.end as usize))
            .collect();
        assert_eq!(held.receive(&tiles, &bodies), 0);
        assert_eq!(held.held(), 2);
        let (x, z) = (-250.0, -150.0);
        assert_eq!(held.height_at(x, z), Some(h.height_at(x, z)));
        // A corrupt body is refused and counted.
        let mut bad = bodies[0].to_vec();
        bad[3] ^= 0xFF;
        let (t3, _) = held.tiles_to_load(Vec3::ZERO, 1e4, &[]);
        assert_eq!(held.receive(&t3[..1], &[bytes::Bytes::from(bad)]), 1);
        // The lower bound never exceeds the ground, wherever it is asked.
        let mut rng = canopy_shared::rng::SplitMix64::new(3);
        for _ in 0..2000 {
            let x = -300.0 + 596.0 * rng.next_f64() as f32;
            let z = -180.0 + 356.0 * rng.next_f64() as f32;
            let (w, d) = (40.0 * rng.next_f64() as f32, 40.0 * rng.next_f64() as f32);
            let r = [x, z, (x + w).min(296.0), (z + d).min(176.0)];
            let lo = held.lowest_in(r);
            for k in 0..25 {
                let (px, pz) = (
                    r[0] + (r[2] - r[0]) * (k % 5) as f32 / 4.0,
                    r[1] + (r[3] - r[1]) * (k / 5) as f32 / 4.0,
                );
                assert!(
                    lo <= h.height_at(px, pz) + 1e-4,
                    "{r:?}: {lo} above the ground at {px}, {pz}"
                );
            }
        }
        assert_eq!(held.lowest_in([-400.0, 0.0, -350.0, 10.0]), f32::NEG_INFINITY);
        let full = HeldTerrain::from_heightfield(&h);
        assert_eq!(full.held(), full.records.len());
        assert!(full.lowest_in([-100.0, -100.0, -60.0, -60.0]) >= held.lowest_in([-100.0, -100.0, -60.0, -60.0]));
    }

    #[test]
    fn tile_meshes_face_up_and_lie_on_the_surface() {
        let h = field();
        let full = HeldTerrain::from_heightfield(&h);
        let (_, s) = full.held_tiles().next().expect("a tile");
        let m = tile_mesh(&h.grid, s);
        assert_eq!(m.positions.len(), (s.size[0] * s.size[1]) as usize);
        for t in m.indices.chunks_exact(3) {
            let [a, b, c] = [0, 1, 2].map(|k| m.positions[t[k] as usize]);
            assert!((b - a).cross(c - a).y > 0.0, "faces up");
            let centre = (a + b + c) / 3.0;
            assert!((h.height_at(centre.x, centre.z) - centre.y).abs() < 1e-3);
        }
        assert!(m.normals.iter().all(|n| n.y > 0.0 && (n.length() - 1.0).abs() < 1e-4));
    }
}
