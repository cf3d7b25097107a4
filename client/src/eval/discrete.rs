//! The usual alternative to progressive streaming, as real files and real requests: each model's
//! discrete LOD files (levels and thresholds: [`canopy_shared::discrete`]), each a whole `.glb`
//! the server wrote beside the `.ctree` and the manifest names, downloaded whole the first time
//! a tree needs it, then kept (no eviction, which favours it).
//!
//! Contract: every frame, [`DiscreteFiles::update`] takes what has arrived, chooses each visible
//! tree's level from its projected height, and asks for the files it lacks, coarse to fine as a
//! progressive glTF viewer does (a tree holding nothing asks for its billboard level first, then
//! its own level). A tree is drawn at its level when held, else at the held level nearest to it
//! (a finer one first), else not at all. Requests go on the method's own source, so on a modelled
//! link they take the link's time and share its connections. Bytes are the bodies received.
//!
//! What is drawn is taken from the `.ctree` decoded whole, at the level's rate: the bake writes
//! each level file from exactly that content (the server's `discrete_files`), so the picture is
//! the level's and the bytes and time are the real file's.
//!
//! The same type is the whole-file baseline ([`DiscreteFiles::whole`]): each visible model's one
//! file (its finest `.glb`, or its `.ctree`), asked for nearest trees first, and a tree drawn at
//! full detail (the caller's full-detail entry) once its model's file has arrived, not before:
//! what a glTF viewer does.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use canopy_shared::discrete::{BILLBOARD_LEVEL, LEVEL_COUNT, LEVEL_RATES, level_for};
use canopy_shared::format::atlas::AtlasLayoutKind;
use canopy_shared::manifest::Manifest;
use tokio::sync::mpsc;

use super::EvalScene;
use crate::lod::projection::BillboardKind;
use crate::net::{NetError, RangeSource};
use crate::stream::{Camera, Drawn, DrawnTree, Viewport};

/// (model index, level).
type Key = (usize, u8);

/// Which file of each model the whole-file baseline downloads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WholeFile {
    /// Level 0 of its discrete files: quantized, meshopt-compressed, every leaf.
    Glb,
    /// The `.ctree` (it also holds the atlases, hulls and clouds).
    Ctree,
}

/// The discrete-files method, or the whole-file baseline (see the module doc).
#[derive(Debug)]
pub struct DiscreteFiles<S> {
    src: Arc<S>,
    /// The whole-file baseline: one file per model (level 0 of `urls`), no billboard level.
    whole: bool,
    /// Level file URLs per model, level 0 first (empty: the manifest names none).
    urls: Vec<Vec<String>>,
    geometry_px: f32,
    held: BTreeSet<Key>,
    asked: BTreeSet<Key>,
    tx: mpsc::UnboundedSender<(Key, Result<u64, NetError>)>,
    rx: mpsc::UnboundedReceiver<(Key, Result<u64, NetError>)>,
    /// Body bytes received so far.
    pub bytes: u64,
    /// Requests sent so far (retries included).
    pub requests: u64,
    /// Requests that failed (each asked again on a later frame).
    pub failures: u64,
}

impl<S: RangeSource> DiscreteFiles<S> {
    /// The method for the scene `m` on `src`, switching to billboards below `geometry_px`.
    pub fn new(src: Arc<S>, m: &Manifest, geometry_px: f32) -> Self {
        let (tx, rx) = mpsc::unbounded_channel();
        Self {
            src,
            whole: false,
            urls: m
                .models
                .iter()
                .map(|x| {
                    if x.levels.len() == LEVEL_COUNT {
                        x.levels.iter().map(|l| l.url.clone()).collect()
                    } else {
                        Vec::new()
                    }
                })
                .collect(),
            geometry_px,
            held: BTreeSet::new(),
            asked: BTreeSet::new(),
            tx,
            rx,
            bytes: 0,
            requests: 0,
            failures: 0,
        }
    }

    /// The whole-file baseline on `src`: each model's `file`, downloaded whole.
    pub fn whole(src: Arc<S>, m: &Manifest, file: WholeFile) -> Self {
        let mut d = Self::new(src, m, 0.0);
        d.whole = true;
        for (urls, x) in d.urls.iter_mut().zip(&m.models) {
            *urls = match file {
                WholeFile::Glb => urls.first().cloned().into_iter().collect(),
                WholeFile::Ctree => vec![x.url.clone()],
            };
        }
        d
    }

    /// Models of the scene with no level files in its manifest.
    pub fn models_without_levels(&self) -> usize {
        self.urls.iter().filter(|u| u.is_empty()).count()
    }

    /// The source the files come over.
    pub fn source(&self) -> &Arc<S> {
        &self.src
    }

    /// Level files not arrived yet.
    pub fn pending(&self) -> usize {
        self.asked.len()
    }

    fn ask(&mut self, key: Key) {
        let Some(url) = self.urls.get(key.0).and_then(|u| u.get(usize::from(key.1))) else {
            return;
        };
        if self.held.contains(&key) || !self.asked.insert(key) {
            return;
        }
        self.requests += 1;
        let (src, url, tx) = (Arc::clone(&self.src), url.clone(), self.tx.clone());
        let token = self.src.task();
        tokio::spawn(async move {
            let _token = token;
            let r = src.get(&url).await.map(|b| b.len() as u64);
            let _ = tx.send((key, r));
        });
    }

    /// Takes the files that have arrived (their bytes count from now).
    pub fn receive(&mut self) {
        while let Ok((key, r)) = self.rx.try_recv() {
            self.asked.remove(&key);
            match r {
                Ok(n) => {
                    self.bytes += n;
                    self.held.insert(key);
                }
                Err(_) => self.failures += 1,
            }
        }
    }

    /// Takes what has arrived, asks for what `trees` (the visible trees, any representation)
    /// need at `cam`, and returns what this method draws now (see the module doc).
    pub fn update(&mut self, scene: &EvalScene, trees: &[DrawnTree], cam: &Camera, vp: &Viewport) -> Vec<DrawnTree> {
        self.receive();
        if self.whole {
            return self.update_whole(scene, trees, cam, vp);
        }
        // Each tree's level, and per model the largest projected height wanting a level (the
        // order requests go out in: billboards first, then the nearest trees' levels).
        let mut wanted: Vec<(usize, u8, f32)> = Vec::with_capacity(trees.len());
        for t in trees {
            let Some(px) = super::projected_px(scene, t, cam, vp, vp.height) else {
                continue;
            };
            wanted.push((usize::from(t.instance.model), level_for(px, self.geometry_px), px));
        }
        let mut asks: BTreeMap<Key, f32> = BTreeMap::new();
        for &(m, level, px) in &wanted {
            let holds_any = (0..LEVEL_COUNT as u8).any(|k| self.held.contains(&(m, k)));
            if !holds_any {
                asks.insert((m, BILLBOARD_LEVEL), f32::INFINITY);
            }
            let e = asks.entry((m, level)).or_insert(0.0);
            *e = e.max(px);
        }
        let mut order: Vec<(Key, f32)> = asks.into_iter().collect();
        order.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        for (key, _) in order {
            self.ask(key);
        }
        let mut out = Vec::with_capacity(trees.len());
        for (t, &(m, level, _)) in trees
            .iter()
            .filter(|t| {
                scene
                    .models
                    .get(usize::from(t.instance.model))
                    .is_some_and(Option::is_some)
            })
            .zip(&wanted)
        {
            let Some(level) = self.drawable(m, level) else {
                continue;
            };
            let Some(model) = scene.models.get(m).and_then(Option::as_ref) else {
                continue;
            };
            let what = if let Some(&rate) = LEVEL_RATES.get(usize::from(level)) {
                Drawn::Geometry {
                    leaves: model
                        .tree
                        .node_leaves
                        .iter()
                        .map(|v| canopy_shared::format::leaf::keep_count(v.len() as u32, rate))
                        .collect(),
                    enlargement_cap: 1.0,
                    iterations: model.last_iteration(),
                }
            } else {
                let frames = model
                    .atlas
                    .as_ref()
                    .and_then(|(t, _)| t.layouts.iter().find(|l| l.kind == AtlasLayoutKind::CrossedQuads))
                    .map(|l| {
                        (l.first_frame..l.first_frame + l.frame_count())
                            .map(|f| (f, 0u8, 0.5))
                            .collect()
                    })
                    .unwrap_or_default();
                Drawn::Billboard {
                    kind: BillboardKind::Crossed,
                    frames,
                }
            };
            out.push(DrawnTree {
                instance: t.instance.clone(),
                what,
            });
        }
        out
    }

    /// [`Self::update`] of the whole-file baseline: `trees` are at full detail, and each is drawn
    /// as it is once its model's file is held.
    fn update_whole(&mut self, scene: &EvalScene, trees: &[DrawnTree], cam: &Camera, vp: &Viewport) -> Vec<DrawnTree> {
        let mut asks: BTreeMap<usize, f32> = BTreeMap::new();
        for t in trees {
            let m = usize::from(t.instance.model);
            if let Some(px) = super::projected_px(scene, t, cam, vp, vp.height) {
                let e = asks.entry(m).or_insert(0.0);
                *e = e.max(px);
            }
        }
        let mut order: Vec<(usize, f32)> = asks.into_iter().collect();
        order.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        for (m, _) in order {
            self.ask((m, 0));
        }
        trees
            .iter()
            .filter(|t| self.held.contains(&(usize::from(t.instance.model), 0)))
            .cloned()
            .collect()
    }

    /// The level model `m` is drawn at when it wants `level`: that one when held, else the held
    /// level nearest to it, a finer one first.
    fn drawable(&self, m: usize, level: u8) -> Option<u8> {
        (0..LEVEL_COUNT as u8)
            .filter(|&k| self.held.contains(&(m, k)))
            .min_by_key(|&k| (k.abs_diff(level), k > level))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::net::NetStats;
    use bytes::Bytes;

    #[derive(Debug, Default)]
    struct Files(NetStats);

    impl RangeSource for Files {
        async fn get(&self, path: &str) -> Result<Bytes, NetError> {
            Ok(Bytes::from(vec![0u8; path.len()]))
        }
        async fn fetch(&self, _: &str, _: &[crate::net::ByteRange]) -> Result<Vec<Bytes>, NetError> {
            Ok(Vec::new())
        }
        fn stats(&self) -> &NetStats {
            &self.0
        }
    }

    fn two_models() -> Manifest {
        Manifest::parse(
            br#"{"format":"canopy-scene","format_version":1,"scene":"s","name":"s","version":1,
            "bounds":{"min":[0,0],"max":[1,1]},"instance_count":0,
            "models":[{"name":"a","url":"/assets/trees/a.ctree","sha256":"00","size":1,
              "levels":[{"url":"/assets/l0","sha256":"0","size":1},{"url":"/assets/l1","sha256":"0","size":1},
                        {"url":"/assets/l2","sha256":"0","size":1},{"url":"/assets/l3","sha256":"0","size":1}]},
              {"name":"b","url":"/assets/trees/b.ctree","sha256":"00","size":1}],
            "pack":{"url":"/assets/p","sha256":"0","size":0,"tables_len":0},"tiles":[]}"#,
        )
        .unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn the_whole_file_baseline_draws_a_tree_only_once_its_file_is_in() {
        let m = two_models();
        let glb = DiscreteFiles::whole(Arc::new(Files::default()), &m, WholeFile::Glb);
        assert_eq!(glb.urls, [vec!["/assets/l0".to_string()], Vec::new()]);
        let mut ctree = DiscreteFiles::whole(Arc::new(Files::default()), &m, WholeFile::Ctree);
        assert_eq!(
            ctree.urls,
            [
                vec!["/assets/trees/a.ctree".to_string()],
                vec!["/assets/trees/b.ctree".to_string()]
            ]
        );
        let tree = |id: u32, model: u16| DrawnTree {
            instance: canopy_shared::pack::PackInstance {
                id,
                model,
                position: [0.0; 3],
                rotation: 0.0,
                scale: 1.0,
            },
            what: Drawn::Geometry {
                leaves: vec![7],
                enlargement_cap: 1.0,
                iterations: 3,
            },
        };
        let trees = [tree(1, 0), tree(2, 1), tree(3, 0)];
        let scene = EvalScene::new(2);
        let (cam, vp) = (
            Camera {
                eye: glam::Vec3::ZERO,
                yaw: 0.0,
                pitch: 0.0,
            },
            Viewport::default(),
        );
        assert!(
            ctree.update(&scene, &trees, &cam, &vp).is_empty(),
            "nothing held, nothing drawn"
        );
        ctree.held.insert((0, 0));
        let drawn = ctree.update(&scene, &trees, &cam, &vp);
        assert_eq!(
            drawn,
            [trees[0].clone(), trees[2].clone()],
            "model 0's trees, as full detail has them"
        );
    }

    #[tokio::test]
    async fn the_nearest_held_level_is_drawn_finer_first() {
        let m = two_models();
        let mut d = DiscreteFiles::new(Arc::new(Files::default()), &m, 150.0);
        assert_eq!(d.models_without_levels(), 1);
        assert_eq!(d.drawable(0, 1), None);
        d.held.insert((0, 3));
        assert_eq!(d.drawable(0, 0), Some(3));
        d.held.insert((0, 0));
        d.held.insert((0, 2));
        assert_eq!(d.drawable(0, 1), Some(0), "finer first at equal distance");
        assert_eq!(d.drawable(0, 3), Some(3));
        // A model the manifest names no levels for asks for nothing.
        d.ask((1, 0));
        assert_eq!(d.requests, 0);
        d.ask((0, 1));
        d.ask((0, 1));
        assert_eq!(d.requests, 1, "a file is asked once");
        for _ in 0..100 {
            tokio::task::yield_now().await;
            if let Ok((key, r)) = d.rx.try_recv() {
                assert_eq!(key, (0, 1));
                assert_eq!(r.ok(), Some("/assets/l1".len() as u64));
                return;
            }
        }
        panic!("the level file never arrived");
    }
}
