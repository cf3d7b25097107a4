//! The models stage: each manifest model's state (closed, open with its index, failed) and its
//! opening. An open model's [`ModelIndex`] is never written after the opening.

pub(crate) mod index;
pub mod open;

use std::collections::BTreeSet;

pub(crate) use index::SegmentsByRadius;
pub(crate) use index::{ModelIndex, Unit};
use open::{GeometryPart, OpenError, OpeningReads, open_model};

use crate::lod::projection::{BillboardKind, Representation};
use crate::net::RangeSource;
use crate::scene::Manifest;

#[derive(Debug)]
pub(crate) enum ModelState {
    /// Not opened yet; `Some(reason)` when the last opening failed a check (tried again).
    Closed(Option<String>),
    Open(Box<ModelIndex>),
    Failed(String),
}

#[derive(Debug)]
pub(crate) struct Model {
    pub url: String,
    size: u64,
    pub state: ModelState,
    /// Why the geometry part cannot be opened (the model stays drawn as stand-ins).
    geometry_failed: Option<String>,
}

/// Every model of the manifest.
#[derive(Debug, Default)]
pub(crate) struct Models {
    list: Vec<Model>,
}

impl Models {
    /// Every model closed.
    pub fn new(manifest: &Manifest) -> Self {
        Self {
            list: manifest
                .models
                .iter()
                .map(|m| Model {
                    url: m.url.clone(),
                    size: m.size,
                    state: ModelState::Closed(None),
                    geometry_failed: None,
                })
                .collect(),
        }
    }

    pub fn len(&self) -> usize {
        self.list.len()
    }

    pub fn as_slice(&self) -> &[Model] {
        &self.list
    }

    pub fn state(&self, m: usize) -> Option<&ModelState> {
        self.list.get(m).map(|x| &x.state)
    }

    /// Model `m`'s index, if it is open.
    pub fn index(&self, m: usize) -> Option<&ModelIndex> {
        match &self.list.get(m)?.state {
            ModelState::Open(i) => Some(i),
            _ => None,
        }
    }

    /// Model `m`'s URL.
    pub fn url(&self, m: usize) -> &str {
        &self.list[m].url
    }

    /// Models that could not be opened (name, reason).
    pub fn failed(&self, manifest: &Manifest) -> Vec<(String, String)> {
        self.list
            .iter()
            .zip(&manifest.models)
            .filter_map(|(m, mm)| match (&m.state, &m.geometry_failed) {
                (ModelState::Failed(e), _) => Some((mm.name.clone(), e.clone())),
                (_, Some(e)) => Some((mm.name.clone(), format!("geometry: {e}"))),
                _ => None,
            })
            .collect()
    }

    /// Whether model `m` is open with its stand-ins only, its geometry part neither opened nor
    /// failed.
    pub fn lacks_geometry(&self, m: usize) -> bool {
        self.index(m).is_some_and(|i| !i.has_geometry()) && self.list[m].geometry_failed.is_none()
    }

    /// Model `m`'s geometry part arrived (or failed): returns what its request read (when it
    /// was added) and whether it read corrupt bytes.
    pub fn receive_geometry(
        &mut self,
        m: usize,
        result: Result<(GeometryPart, OpeningReads), OpenError>,
    ) -> (Option<OpeningReads>, bool) {
        let model = &mut self.list[m];
        let ModelState::Open(idx) = &mut model.state else {
            return (None, false);
        };
        match result.and_then(|(part, reads)| idx.add_geometry(part).map(|()| reads)) {
            Ok(reads) => (Some(reads), false),
            Err(OpenError::Retry) => (None, false),
            Err(OpenError::Corrupt(_)) => (None, true),
            Err(OpenError::Fatal(e)) => {
                model.geometry_failed = Some(e);
                (None, false)
            }
        }
    }

    /// Models whose last opening failed a check (name, reason): tried again each frame.
    pub fn retrying(&self, manifest: &Manifest) -> Vec<(String, String)> {
        self.list
            .iter()
            .zip(&manifest.models)
            .filter_map(|(m, mm)| match &m.state {
                ModelState::Closed(Some(e)) => Some((mm.name.clone(), e.clone())),
                _ => None,
            })
            .collect()
    }

    /// Whether some model is neither open nor failed.
    pub fn any_closed(&self) -> bool {
        self.list.iter().any(|m| matches!(m.state, ModelState::Closed(_)))
    }

    /// The closed models among `wanted` not in `opening`: (model, url, size).
    pub fn to_open(&self, wanted: BTreeSet<usize>, opening: &BTreeSet<usize>) -> Vec<(usize, String, u64)> {
        wanted
            .into_iter()
            .filter(|m| !opening.contains(m))
            .filter(|&m| matches!(self.list[m].state, ModelState::Closed(_)))
            .map(|m| (m, self.list[m].url.clone(), self.list[m].size))
            .collect()
    }

    /// Model `m`'s opening ended: its state follows; returns what the opening read (when it
    /// opened) and whether it read corrupt bytes.
    pub fn receive(
        &mut self,
        m: usize,
        result: Result<(ModelIndex, OpeningReads), OpenError>,
    ) -> (Option<OpeningReads>, bool) {
        let mut out = (None, false);
        self.list[m].state = match result {
            Ok((idx, reads)) => {
                out.0 = Some(reads);
                ModelState::Open(Box::new(idx))
            }
            Err(OpenError::Retry) => ModelState::Closed(None),
            Err(OpenError::Corrupt(e)) => {
                out.1 = true;
                ModelState::Closed(Some(e.to_string()))
            }
            Err(OpenError::Fatal(e)) => ModelState::Failed(e),
        };
        out
    }
}

/// What opening one tree file read and found, for tools that plan without streaming
/// (`canopy plan`).
#[derive(Debug, Clone)]
pub struct OpenedTree {
    /// Leaf blocks, band-major, offsets relative to the leaves section.
    pub layout: canopy_shared::format::BandLayout,
    /// The leaves section's absolute offset.
    pub leaves_offset: u64,
    /// Bytes the opening requests read.
    pub bytes_read: u64,
}

/// Opens the tree at `url` (`size` bytes) exactly as the streamer opens a model.
pub async fn open_tree<S: RangeSource>(src: &S, url: &str, size: u64) -> Result<OpenedTree, String> {
    match open_model(src, url, size).await {
        Ok((idx, (ranges, _))) => Ok(OpenedTree {
            bytes_read: ranges.iter().map(|r| r.end - r.start).sum(),
            layout: idx.layout,
            leaves_offset: idx.leaves_offset,
        }),
        Err(OpenError::Retry) => Err("the read failed (a network or file error worth retrying)".into()),
        Err(OpenError::Corrupt(e)) => Err(e.to_string()),
        Err(OpenError::Fatal(m)) => Err(m),
    }
}

/// Representation of a tree, moved down the ladder past what the model lacks (geometry too,
/// until the model's geometry part has been opened).
pub(crate) fn supported(idx: &ModelIndex, rep: Representation) -> Representation {
    let has_hull = idx.hull.as_ref().is_some_and(|h| !h.levels.is_empty());
    let has_atlas = idx.atlas.as_ref().is_some_and(|a| !a.frames.is_empty());
    match rep {
        Representation::Geometry | Representation::Iterations { .. } if !idx.has_geometry() => {
            if idx.crossed.is_some() {
                // The stand-in, which every tree fetches first anyway.
                Representation::Billboard(BillboardKind::Crossed)
            } else if has_atlas && !has_hull {
                Representation::Billboard(BillboardKind::HemiOct)
            } else {
                // The coarsest hull, which every tree fetches first anyway; with no hull at all
                // the tree is pending (resolve finds no level to draw) until the geometry part
                // arrives.
                Representation::Hull { level: 255 }
            }
        }
        Representation::Hull { .. } if !has_hull => {
            if has_atlas {
                Representation::Billboard(BillboardKind::HemiOct)
            } else {
                Representation::Geometry
            }
        }
        // A model baked without irregular views draws the regular grid's blend instead.
        Representation::Billboard(BillboardKind::Views)
            if has_atlas && idx.atlas.as_ref().is_some_and(|a| a.views.is_none()) =>
        {
            Representation::Billboard(BillboardKind::HemiOct)
        }
        Representation::Billboard(_) if !has_atlas => {
            if has_hull {
                Representation::Hull { level: 255 }
            } else {
                Representation::Geometry
            }
        }
        // An import has no iterations to leave out.
        Representation::Iterations { .. } if idx.directory.iterations == 0 => Representation::Geometry,
        Representation::CloudLevel(l) => match &idx.cloud {
            Some(c) => Representation::CloudLevel(l.min(u8::try_from(c.levels.len() - 1).unwrap_or(u8::MAX))),
            None => supported(idx, Representation::Billboard(BillboardKind::HemiOct)),
        },
        r => r,
    }
}
