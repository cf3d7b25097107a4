//! The resolve stage: what each selected tree can be drawn as *from what the client holds*. A
//! tree whose wanted representation is not held yet falls back to its model's crossed-quad
//! stand-in at the finest resolution held (a tree that wanted a hull: to a held hull level first,
//! the wanted one, else the finest), else to a held hull level, so a slow or failing link
//! degrades the picture, never corrupts it; a tree with nothing held is pending.
//!
//! Geometry draws the first leaves of each node up to its held band prefix; clouds and
//! billboards draw the wanted levels and frames that are held, weights renormalised over them.
//!
//! Reads the selection and the residency; returns the frame's counts, the drawn trees and the
//! units in use (which the residency marks, [`super::residency::Residency::touch`]).

use super::billboard::FrameSet;
use super::geometry::{TreeState, geo_keep};
use super::instances::Instances;
use super::model::Models;
use super::report::{Drawn, DrawnTree, FrameReport, rate_bin};
use super::residency::Residency;
use super::select::Selection;
use crate::cache::{BlockKey, FrameTouches, ModelId};
use crate::lod::bark::BARK_MIN_RADII;
use crate::lod::projection::{BillboardKind, Representation};

/// Share of its wanted leaves a geometry tree must hold to be drawn as geometry rather than as
/// its model's crossed-quad stand-in (0: as soon as its skeleton is here).
pub(crate) const STAND_IN_LEAF_SHARE: f64 = 0.25;

/// What the frame drew.
#[derive(Debug, Default)]
pub(crate) struct Resolved {
    /// The frame's draw counts (the other report fields are the frame loop's).
    pub report: FrameReport,
    /// Each drawn tree, in instance order.
    pub drawn: Vec<DrawnTree>,
    /// Per drawn model, the units in use, in key order.
    pub touches: Vec<FrameTouches>,
}

/// Per model, what every draw of it reads, looked up once per frame.
struct ModelDraw {
    /// Leaf triangles at full detail.
    leaf_triangles: u64,
    /// Bark triangles of the whole skeleton in each bark variant.
    bark_triangles: [u64; BARK_MIN_RADII.len()],
    /// Largest `k` whose skeleton iterations `0..=k` are all held (`None`: not even the first):
    /// a geometry draw shows at most these iterations.
    held_iterations: Option<u8>,
    /// Fewest iterations a geometry draw may show (the ladder's largest `iterN` below the
    /// model's last); with fewer held the tree falls back to a stand-in.
    min_iterations: u8,
    /// The model's last iteration.
    last_iteration: u8,
    /// Triangles of each hull level held.
    hull_cached: Vec<Option<u32>>,
    /// Per atlas image (`frame × resolutions + resolution`): whether it is held, once looked up.
    image_cached: Vec<Option<bool>>,
    /// The crossed-quad stand-in's frames and the finest resolution at which both are held.
    crossed_held: Option<([u32; 2], u8)>,
    /// Planes of each cloud level held.
    cloud_cached: Vec<Option<u32>>,
    used_clouds: Vec<bool>,
    resolutions: usize,
    /// Most leaves any drawn instance keeps of each leaf node.
    max_keep: Vec<u32>,
    used_hull: Vec<bool>,
    used_images: Vec<bool>,
}

impl ModelDraw {
    fn new(models: &Models, residency: &Residency, m: usize, max_dropped: u8) -> Option<Self> {
        let idx = models.index(m)?;
        let held = |key| residency.contains(m, key);
        let hull_cached: Vec<Option<u32>> = idx.hull.as_ref().map_or_else(Vec::new, |h| {
            (0..h.levels.len())
                .map(|l| held(BlockKey::Hull { level: l as u16 }).then_some(h.levels[l].triangles))
                .collect()
        });
        let (frames, res) = idx
            .atlas
            .as_ref()
            .map_or((0, 1), |a| (a.frames.len(), a.resolutions.len().max(1)));
        let cloud_cached: Vec<Option<u32>> = idx.cloud.as_ref().map_or_else(Vec::new, |c| {
            c.levels
                .iter()
                .enumerate()
                .map(|(l, e)| held(BlockKey::Cloud { level: l as u8 }).then_some(e.plane_count))
                .collect()
        });
        let crossed_held = idx.crossed.and_then(|fr| {
            (0..res as u8)
                .find(|&r| fr.iter().all(|&frame| held(BlockKey::Atlas { frame, resolution: r })))
                .map(|r| (fr, r))
        });
        let bark_triangles = residency.bark_triangles(m, idx);
        let table = &idx.directory.iteration_table;
        let mut held_iterations = None;
        for k in 0..table.len() {
            let start = if k == 0 { 0 } else { table[k - 1].skeleton_bytes_end };
            let empty = table[k].skeleton_bytes_end <= start;
            if !empty && !held(BlockKey::Skeleton { iteration: k as u8 }) {
                break;
            }
            held_iterations = Some(k as u8);
        }
        let last = table.len().saturating_sub(1) as u8;
        Some(Self {
            crossed_held,
            used_clouds: vec![false; cloud_cached.len()],
            cloud_cached,
            leaf_triangles: 2 * u64::from(idx.directory.leaf_count),
            bark_triangles,
            held_iterations: held_iterations.filter(|_| idx.has_geometry()),
            min_iterations: idx.drawn_iterations(max_dropped),
            last_iteration: last,
            used_hull: vec![false; hull_cached.len()],
            hull_cached,
            image_cached: vec![None; frames * res],
            used_images: vec![false; frames * res],
            resolutions: res,
            max_keep: vec![0; idx.leaf_nodes.len()],
        })
    }
}

/// Resolves every selected draw against what is held. The held band prefixes of the models drawn
/// as geometry must be current ([`Residency::refresh_held_bands`]).
pub(crate) fn resolve(
    models: &Models,
    instances: &Instances,
    trees: &[TreeState],
    sel: &Selection,
    residency: &Residency,
    max_dropped: u8,
) -> Resolved {
    let mut rep = FrameReport::default();
    let mut drawn_list = Vec::with_capacity(sel.draws.len());
    let mut per_model: Vec<Option<ModelDraw>> = (0..models.len()).map(|_| None).collect();
    // Held band prefixes of the models drawn as geometry.
    let held_bands = |m: usize| {
        sel.needs
            .get(m)
            .is_some_and(|n| n.geometry)
            .then(|| residency.held_bands(m))
            .flatten()
    };
    for d in &sel.draws {
        let Some(idx) = models.index(d.model) else { continue };
        let slot = &mut per_model[d.model];
        if slot.is_none() {
            *slot = ModelDraw::new(models, residency, d.model, max_dropped);
        }
        let Some(md) = slot.as_mut() else { continue };
        let bark = usize::from(d.bark).min(BARK_MIN_RADII.len() - 1);
        rep.full_triangles += md.leaf_triangles + md.bark_triangles[bark];
        // The wanted hull level if cached, else the finest cached one.
        let wanted_hull = match d.rep {
            Representation::Hull { level } => Some(usize::from(level)),
            _ => None,
        };
        let hull_any = wanted_hull
            .into_iter()
            .chain(0..md.hull_cached.len())
            .find_map(|l| md.hull_cached.get(l).copied().flatten().map(|t| (l, t)));
        let mut drew = None;
        // Geometry shows the wanted iterations once the skeleton its bark draws is held (the
        // skeleton drawn, the leaves of every wanted iteration), or fewer while later ones stream
        // in (no fewer than the ladder's coarsest iteration rung; skeleton and leaves alike).
        let drawable = match (d.rep.is_geometry(), md.held_iterations, sel.geo.get(d.geo as usize)) {
            (true, Some(h), Some(g)) if h >= g.skeleton_iterations => Some((h.min(g.iterations), g.iterations)),
            (true, Some(h), Some(g)) if h >= md.min_iterations.min(g.iterations) => {
                Some((h.min(g.iterations), h.min(g.iterations)))
            }
            _ => None,
        };
        match d.rep {
            Representation::Geometry | Representation::Iterations { .. } if drawable.is_some() => {
                let (Some(g), Some((iterations, leaf_iterations))) = (sel.geo.get(d.geo as usize), drawable) else {
                    continue;
                };
                let keep = geo_keep(trees, g, idx);
                let leaf_iteration = &idx.lod.leaf_iteration;
                let present: &[u32] = held_bands(d.model).map_or(&[], |h| &h.present);
                let (mut leaves, mut wanted) = (0u64, 0u64);
                let mut per_node = vec![0u32; keep.len()];
                let mut bins = [0u64; 10];
                let counts = idx.layout.leaf_counts();
                for (o, &k) in keep.iter().enumerate() {
                    // Leaf nodes of branches not drawn (yet) are left out.
                    if k == 0 || leaf_iteration.get(o).is_some_and(|&it| it > leaf_iterations) {
                        continue;
                    }
                    md.max_keep[o] = md.max_keep[o].max(k);
                    let drawn = k.min(present.get(o).copied().unwrap_or(0));
                    per_node[o] = drawn;
                    leaves += u64::from(drawn);
                    wanted += u64::from(k);
                    bins[rate_bin(drawn, counts[o])] += 1;
                }
                // Too few of its leaves here: the tree stays its stand-in, a bare skeleton
                // looking less like it (its held leaves are touched all the same, so the cache
                // keeps them).
                if md.crossed_held.is_some() && (leaves as f64) < STAND_IN_LEAF_SHARE * wanted as f64 {
                    rep.geometry_waiting += 1;
                } else {
                    for (h, b) in rep.rate_histogram.iter_mut().zip(bins) {
                        *h += b;
                    }
                    rep.leaves += leaves;
                    rep.triangles += 2 * leaves;
                    rep.triangles += if iterations >= md.last_iteration {
                        md.bark_triangles[bark]
                    } else {
                        residency.bark_triangles_through(d.model, idx, iterations, bark)
                    };
                    rep.geometry_trees += 1;
                    drew = Some(Drawn::Geometry {
                        leaves: per_node,
                        enlargement_cap: g.budget.enlargement_cap,
                        iterations,
                    });
                }
            }
            Representation::CloudLevel(want) => {
                // The wanted levels that are held; else the held level nearest the first.
                let mut levels: Vec<(u8, f32)> = d
                    .clouds
                    .iter()
                    .filter(|&&(l, w)| w > 0.0 && md.cloud_cached.get(usize::from(l)).copied().flatten().is_some())
                    .copied()
                    .collect();
                if levels.is_empty()
                    && let Some(l) = (0..md.cloud_cached.len())
                        .filter(|&l| md.cloud_cached[l].is_some())
                        .min_by_key(|&l| l.abs_diff(usize::from(want)))
                {
                    levels.push((l as u8, 1.0));
                }
                let total: f32 = levels.iter().map(|l| l.1).sum();
                if total > 0.0 {
                    levels.sort_by(|a, b| b.1.total_cmp(&a.1));
                    let mut planes = 0u64;
                    for (l, w) in &mut levels {
                        *w /= total;
                        md.used_clouds[usize::from(*l)] = true;
                        planes += u64::from(md.cloud_cached[usize::from(*l)].unwrap_or(0));
                    }
                    rep.cloud_trees += 1;
                    rep.cloud_blends += usize::from(levels.len() > 1);
                    rep.cloud_planes += planes;
                    rep.triangles += 2 * planes;
                    drew = Some(Drawn::Cloud { levels });
                }
            }
            Representation::Billboard(kind) => {
                let mut held = FrameSet::default();
                for &(f, r, w) in d.frames.as_slice() {
                    // The wanted image, else the nearest finer one held (drawn minified): the
                    // schedule does not fetch an image whose finer one is held or coming.
                    for r in (0..=r).rev() {
                        let k = f as usize * md.resolutions + usize::from(r);
                        let is_held = match md.image_cached.get_mut(k) {
                            Some(Some(h)) => *h,
                            Some(slot) => *slot.insert(residency.contains(
                                d.model,
                                BlockKey::Atlas {
                                    frame: f,
                                    resolution: r,
                                },
                            )),
                            None => false,
                        };
                        if is_held {
                            held.push((f, r, w));
                            md.used_images[k] = true;
                            break;
                        }
                    }
                }
                if held.len > 0 {
                    let quads = if kind == BillboardKind::Crossed {
                        2
                    } else {
                        u64::from(held.len)
                    };
                    rep.billboard_quads += quads;
                    rep.triangles += 2 * quads;
                    rep.billboard_trees += 1;
                    let total: f32 = held.as_slice().iter().map(|h| h.2).sum();
                    let frames = held
                        .as_slice()
                        .iter()
                        .map(|&(f, r, w)| (f, r, if total > 0.0 { w / total } else { 0.0 }))
                        .collect();
                    drew = Some(Drawn::Billboard { kind, frames });
                }
            }
            _ => {}
        }
        if drew.is_none() {
            // Wanted a hull, or a fallback because what was wanted is not held yet: a tree that
            // wanted a hull draws a held hull level first, any other the crossed-quad stand-in.
            let hull = hull_any.filter(|_| wanted_hull.is_some() || md.crossed_held.is_none());
            if let Some((l, tris)) = hull {
                md.used_hull[l] = true;
                rep.hull_trees += 1;
                rep.triangles += u64::from(tris);
                drew = Some(Drawn::Hull { level: l as u16 });
            } else if let Some((frames, r)) = md.crossed_held {
                for f in frames {
                    md.used_images[f as usize * md.resolutions + usize::from(r)] = true;
                }
                rep.billboard_quads += 2;
                rep.triangles += 4;
                rep.billboard_trees += 1;
                rep.stand_in_trees += 1;
                drew = Some(Drawn::Billboard {
                    kind: BillboardKind::Crossed,
                    frames: frames.iter().map(|&f| (f, r, 0.5)).collect(),
                });
            } else {
                rep.pending_trees += 1;
            }
        }
        if let Some(what) = drew {
            drawn_list.push(DrawnTree {
                instance: instances.list[d.inst as usize].inst.clone(),
                what,
            });
        }
    }
    // Each unit in use is touched once per frame (the cache evicts the least used), in key
    // order: leaves (band, node), hull levels, cloud levels, atlas images.
    let mut touches = Vec::new();
    for (m, md) in per_model.into_iter().enumerate() {
        let Some(md) = md else { continue };
        // Bands drawn of each node: what the neediest instance keeps, as far as it is held
        // (bands needed grow with the keep count, so the maximum keep decides).
        let leaf_bands: Vec<usize> = match (models.index(m), held_bands(m)) {
            (Some(idx), Some(hb)) => md
                .max_keep
                .iter()
                .zip(idx.layout.leaf_counts())
                .zip(&hb.bands)
                .map(|((&k, &n), &h)| h.min(idx.layout.bands_for_keep(n, k)))
                .collect(),
            _ => Vec::new(),
        };
        let res = md.resolutions.max(1);
        let others = set_indices(&md.used_hull)
            .map(|l| BlockKey::Hull { level: l as u16 })
            .chain(set_indices(&md.used_clouds).map(|l| BlockKey::Cloud { level: l as u8 }))
            .chain(set_indices(&md.used_images).map(|k| BlockKey::Atlas {
                frame: (k / res) as u32,
                resolution: (k % res) as u8,
            }))
            .collect();
        touches.push(FrameTouches {
            model: ModelId(m as u32),
            leaf_bands,
            others,
        });
    }
    Resolved {
        report: rep,
        drawn: drawn_list,
        touches,
    }
}

/// Indices of the set flags.
fn set_indices(flags: &[bool]) -> impl Iterator<Item = usize> + '_ {
    flags.iter().enumerate().filter(|(_, f)| **f).map(|(k, _)| k)
}
