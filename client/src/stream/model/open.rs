//! The opening protocol of a model file, and nothing else: one request for the header and
//! directory, then one multi-range request for the node table, materials and the hull, atlas and
//! cloud tables; bigger tables cost one more request each. Decoding and every check are
//! `canopy_shared::format`'s; this module only decides what to ask for.

use std::borrow::Cow;

use bytes::Bytes;
use canopy_shared::format::atlas::AtlasTable;
use canopy_shared::format::cloud::CloudTable;
use canopy_shared::format::directory::SectionKind;
use canopy_shared::format::hull::HullTable;
use canopy_shared::format::materials::decode_materials;
use canopy_shared::format::skeleton_radii::decode_skeleton_radii;
use canopy_shared::format::tree::{NodeIndex, decode_index, decode_node_index};
use canopy_shared::format::{Directory, FIRST_REQUEST_LEN, FormatError, HEADER_LEN, Header, SectionEntry, check_crc};

use super::index::{LodTables, ModelIndex};
use crate::net::{ByteRange, NetError, RangeSource};
use crate::plan::merge_ranges;

/// Bytes asked for when opening a model: header and directory (the directory of the
/// 293,000-leaf linden is 660 bytes with the header).
pub const OPEN_REQUEST_LEN: u64 = 4096;

/// Bytes of the billboard-cloud section asked for when a model opens: the default bake's table
/// (3 levels, ≤ 20 planes, ≤ 1.5 KiB) fits; a bigger table costs one more request.
const CLOUD_TABLE_PREFIX: u64 = 2048;

/// Why a model did not open.
#[derive(Debug)]
pub(crate) enum OpenError {
    /// A network error worth trying again next frame.
    Retry,
    /// Bytes that failed a check (CRC or structure): counted as corrupt, retried next frame.
    Corrupt(FormatError),
    /// The model cannot be opened (missing file, a file that contradicts itself).
    Fatal(String),
}

impl From<NetError> for OpenError {
    fn from(e: NetError) -> Self {
        if e.is_retryable() {
            Self::Retry
        } else {
            Self::Fatal(e.to_string())
        }
    }
}

impl From<FormatError> for OpenError {
    fn from(e: FormatError) -> Self {
        // A corrupt index may be a corrupted transfer: counted, tried again next frame.
        Self::Corrupt(e)
    }
}

/// One range of `url`.
async fn fetch_one<S: RangeSource>(src: &S, url: &str, r: ByteRange) -> Result<Bytes, OpenError> {
    src.fetch(url, std::slice::from_ref(&r))
        .await?
        .pop()
        .ok_or(OpenError::Retry)
}

/// The first `table_len` bytes of section `e` (a hull or atlas table): from `prefix`, the
/// section's first bytes already fetched, when it holds them, else one more request.
async fn section_table<S: RangeSource>(
    src: &S,
    url: &str,
    e: &SectionEntry,
    prefix: &[u8],
    table_len: u32,
) -> Result<Bytes, OpenError> {
    let t = u64::from(table_len);
    if t <= prefix.len() as u64 {
        Ok(Bytes::copy_from_slice(&prefix[..t as usize]))
    } else {
        fetch_one(src, url, e.offset..e.offset + t.min(e.length)).await
    }
}

/// The byte ranges a model's opening requests read, with their bodies: in a small file they
/// also hold leaf blocks, atlas images and the like, which the residency stage keeps rather
/// than fetching them again.
pub(crate) type OpeningReads = (Vec<ByteRange>, Vec<Bytes>);

/// Bytes read so far by one opening: the first read (header and directory) and the merged
/// ranges of the later ones, with their bodies.
struct Reads<'a> {
    first: &'a Bytes,
    merged: Vec<ByteRange>,
    bodies: Vec<Bytes>,
}

impl Reads<'_> {
    /// Fetches `ranges` less what the first read holds, in one multi-range request.
    async fn fetch<'a, S: RangeSource>(
        src: &S,
        url: &str,
        first: &'a Bytes,
        ranges: Vec<ByteRange>,
    ) -> Result<Reads<'a>, OpenError> {
        // What the first request already holds (all of it, in a small file) is not asked again:
        // a table that starts inside it is asked from where it ends.
        let held = first.len() as u64;
        let mut sorted: Vec<ByteRange> = ranges
            .iter()
            .filter(|r| r.end > held)
            .map(|r| r.start.max(held)..r.end)
            .collect();
        sorted.sort_by_key(|r| r.start);
        let merged = merge_ranges(sorted.into_iter());
        let bodies = if merged.is_empty() {
            Vec::new()
        } else {
            src.fetch(url, &merged).await?
        };
        Ok(Reads { first, merged, bodies })
    }

    /// The bytes of `r`, from the first read and the later ones.
    fn slice(&self, r: &ByteRange) -> Option<Cow<'_, [u8]>> {
        let held = self.first.len() as u64;
        if r.end <= held {
            return self.first.get(r.start as usize..r.end as usize).map(Cow::Borrowed);
        }
        let rest = r.start.max(held)..r.end;
        let k = self
            .merged
            .iter()
            .position(|m| m.start <= rest.start && rest.end <= m.end)?;
        let tail = self
            .bodies
            .get(k)?
            .get((rest.start - self.merged[k].start) as usize..(rest.end - self.merged[k].start) as usize)?;
        if r.start >= held {
            return Some(Cow::Borrowed(tail));
        }
        let mut joined = self.first.get(r.start as usize..)?.to_vec();
        joined.extend_from_slice(tail);
        Some(Cow::Owned(joined))
    }
}

/// Opens a model whole: its stand-ins part, then its geometry part.
pub(crate) async fn open_model<S: RangeSource>(
    src: &S,
    url: &str,
    size: u64,
) -> Result<(ModelIndex, OpeningReads), OpenError> {
    let (mut idx, mut reads) = open_stand_ins(src, url, size).await?;
    let (part, more) = open_geometry(src, url, &idx.directory, &idx.head).await?;
    idx.add_geometry(part)?;
    // The head is in both reads.
    reads.0.extend(more.0.into_iter().skip(1));
    reads.1.extend(more.1.into_iter().skip(1));
    Ok((idx, reads))
}

/// Opens what drawing a model's stand-ins needs: header and directory, then the hull, atlas and
/// cloud tables in one multi-range request (a few KiB). The index has no geometry part yet
/// ([`ModelIndex::has_geometry`]): its trees are drawn as stand-ins until [`open_geometry`].
pub(crate) async fn open_stand_ins<S: RangeSource>(
    src: &S,
    url: &str,
    size: u64,
) -> Result<(ModelIndex, OpeningReads), OpenError> {
    // The header and directory of every baked tree fit in a few hundred bytes: ask for
    // OPEN_REQUEST_LEN and fetch the rest of a longer directory (up to FIRST_REQUEST_LEN, the
    // format's bound) only when the header says so.
    let first_len = size.min(OPEN_REQUEST_LEN);
    let mut first = fetch_one(src, url, 0..first_len).await?;
    if first.len() >= HEADER_LEN {
        let header = Header::decode(&first[..HEADER_LEN])?;
        let need = (header.directory_offset + u64::from(header.directory_len)).min(size.min(FIRST_REQUEST_LEN));
        if need > first.len() as u64 {
            first = fetch_one(src, url, 0..need).await?;
        }
    }
    let (_, directory) = decode_index(&first, Some(size))?;
    let sec = |k: SectionKind| directory.section(k).copied();
    if sec(SectionKind::NodeTable).is_none() {
        return Err(OpenError::Fatal("no node table".into()));
    }
    if sec(SectionKind::Materials).is_none() {
        return Err(OpenError::Fatal("no materials".into()));
    }
    let hull_e = sec(SectionKind::Hulls);
    let atlas_e = sec(SectionKind::BillboardAtlases);
    let cloud_e = sec(SectionKind::BillboardClouds);
    // Table prefixes: the hull table is ≤ 484 bytes, the atlas table ~10 KiB and the cloud
    // table ~1 KiB by default. Ask for enough to hold each in one go and fetch the rest of a
    // bigger table after.
    let hull_prefix = hull_e.map(|e| e.offset..e.offset + e.length.min(1024));
    let atlas_prefix = atlas_e.map(|e| e.offset..e.offset + e.length.min(16 * 1024));
    let cloud_prefix = cloud_e.map(|e| e.offset..e.offset + e.length.min(CLOUD_TABLE_PREFIX));
    let mut ranges = Vec::new();
    ranges.extend(hull_prefix.clone().filter(|r| r.end > r.start));
    ranges.extend(atlas_prefix.clone().filter(|r| r.end > r.start));
    ranges.extend(cloud_prefix.clone().filter(|r| r.end > r.start));
    let got = Reads::fetch(src, url, &first, ranges).await?;
    let hull = match (&hull_e, &hull_prefix) {
        (Some(e), Some(r)) if e.length > 0 => {
            let p = got.slice(r).ok_or(OpenError::Retry)?;
            let bytes = section_table(src, url, e, &p, HullTable::peek_table_len(&p)?).await?;
            Some(HullTable::decode(&bytes, e.length)?)
        }
        _ => None,
    };
    let atlas = match (&atlas_e, &atlas_prefix) {
        (Some(e), Some(r)) if e.length > 0 => {
            let p = got.slice(r).ok_or(OpenError::Retry)?;
            let bytes = section_table(src, url, e, &p, AtlasTable::peek_table_len(&p)?).await?;
            Some(AtlasTable::decode(&bytes, e.length)?)
        }
        _ => None,
    };
    let cloud = match (&cloud_e, &cloud_prefix) {
        (Some(e), Some(r)) if e.length > 0 => {
            // Clouds are optional: a table this client cannot use (malformed, or with flags from
            // a newer format) leaves the model without clouds rather than unopened. Only a CRC
            // mismatch, which a corrupted transfer gives, opens the model again.
            let p = got.slice(r).ok_or(OpenError::Retry)?;
            match CloudTable::peek_table_len(&p) {
                Ok(len) => {
                    let bytes = section_table(src, url, e, &p, len).await?;
                    match CloudTable::decode(&bytes, e.length) {
                        Ok(t) => Some(t).filter(|t| !t.levels.is_empty()),
                        Err(err @ FormatError::ChecksumMismatch { .. }) => return Err(err.into()),
                        Err(_) => None,
                    }
                }
                Err(_) => None,
            }
        }
        _ => None,
    };
    let bark_mesh_tris = sec(SectionKind::BarkMesh).map_or(0, |e| u64::from(e.item_count));
    let (lo, hi) = (directory.bounds_min, directory.bounds_max);
    // Until the node table gives the root sphere: the bounds' sphere.
    let center = (lo + hi) * 0.5;
    let radius = (hi - lo).length() * 0.5;
    let mut reads: OpeningReads = (Vec::with_capacity(1 + got.merged.len()), vec![first.clone()]);
    reads.0.push(0..first.len() as u64);
    reads.0.extend(got.merged.iter().cloned());
    reads.1.extend(got.bodies);
    let mut opened = reads.0.clone();
    opened.sort_by_key(|r| r.start);
    let mut index = ModelIndex {
        other_units: Vec::new(),
        crossed: None,
        stand_ins: Vec::new(),
        iteration_radii: None,
        opened,
        lod: LodTables::new(&[], center, &[]),
        height: (hi.y - lo.y.min(0.0)).max(0.01),
        center,
        radius,
        leaf_size: (directory.leaf_width_max * directory.leaf_length_max).sqrt(),
        leaf_material_count: 0,
        materials: canopy_shared::model::Materials::default(),
        bark_mesh_triangles: bark_mesh_tris,
        layout: canopy_shared::format::BandLayout::new(&directory.band_edges, &[]),
        directory,
        leaf_nodes: Vec::new(),
        leaves_offset: 0,
        nodes: Vec::new(),
        hull,
        atlas,
        cloud,
        head: first,
    };
    index.other_units = index.other_units();
    index.crossed = index.find_crossed_frames();
    index.stand_ins = index.find_stand_in_units();
    Ok((index, reads))
}

/// What drawing a model as geometry needs beyond its stand-ins: the node table and materials.
#[derive(Debug)]
pub(crate) struct GeometryPart {
    pub nodes: Vec<canopy_shared::format::NodeRecord>,
    pub leaf_nodes: Vec<usize>,
    pub layout: canopy_shared::format::BandLayout,
    pub leaves_offset: u64,
    pub leaves_len: u64,
    pub materials: canopy_shared::model::Materials,
    /// Thickest branch radius of each skeleton iteration, metres (`None`: the file has no
    /// skeleton-radii section).
    pub iteration_radii: Option<Vec<f32>>,
    /// The byte ranges read.
    pub read: Vec<ByteRange>,
}

/// Opens a model's geometry part (one request for the node table and materials; in a small
/// file the first read may already hold them). Its reads start with the head.
pub(crate) async fn open_geometry<S: RangeSource>(
    src: &S,
    url: &str,
    directory: &Directory,
    head: &Bytes,
) -> Result<(GeometryPart, OpeningReads), OpenError> {
    let sec = |k: SectionKind| directory.section(k).copied();
    let nodes_e = sec(SectionKind::NodeTable).ok_or_else(|| OpenError::Fatal("no node table".into()))?;
    let mats_e = sec(SectionKind::Materials).ok_or_else(|| OpenError::Fatal("no materials".into()))?;
    let radii_e = sec(SectionKind::SkeletonRadii).filter(|e| e.length > 0);
    let mut ranges = vec![nodes_e.range(), mats_e.range()];
    ranges.extend(radii_e.map(|e| e.range()));
    let got = Reads::fetch(src, url, head, ranges).await?;
    let table = got.slice(&nodes_e.range()).ok_or(OpenError::Retry)?;
    let NodeIndex {
        nodes,
        leaf_nodes,
        layout,
        leaves_offset,
        leaves_len,
    } = decode_node_index(directory, &table)?;
    let mats = got.slice(&mats_e.range()).ok_or(OpenError::Retry)?;
    check_crc("materials", &mats, mats_e.crc)?;
    let materials = decode_materials(&mats)?;
    let iteration_radii = match radii_e {
        Some(e) => {
            let b = got.slice(&e.range()).ok_or(OpenError::Retry)?;
            check_crc("skeleton radii", &b, e.crc)?;
            Some(decode_skeleton_radii(
                &b,
                directory.iteration_table.len(),
                directory.radius_max,
            )?)
        }
        None => None,
    };
    // The head first: in a small file it holds leaf blocks, which only the node table locates.
    let mut reads: OpeningReads = (Vec::with_capacity(1 + got.merged.len()), vec![head.clone()]);
    reads.0.push(0..head.len() as u64);
    reads.0.extend(got.merged.iter().cloned());
    reads.1.extend(got.bodies.iter().cloned());
    Ok((
        GeometryPart {
            nodes,
            leaf_nodes,
            layout,
            leaves_offset,
            leaves_len,
            materials,
            iteration_radii,
            read: got.merged,
        },
        reads,
    ))
}

impl ModelIndex {
    /// Adds the geometry part: the model can then be drawn as geometry.
    pub fn add_geometry(&mut self, part: GeometryPart) -> Result<(), OpenError> {
        // Leaf blocks are located from the node table alone: a section of another length would
        // put them on other bytes.
        if part.leaves_len != part.layout.total_len() {
            return Err(OpenError::Fatal(format!(
                "the leaves section is {} bytes, but the node table's leaf counts need {}",
                part.leaves_len,
                part.layout.total_len()
            )));
        }
        let root = part
            .nodes
            .first()
            .ok_or_else(|| OpenError::Fatal("empty node table".into()))?;
        let (lo, hi) = (self.directory.bounds_min, self.directory.bounds_max);
        self.center = root.sphere_center;
        self.radius = root.sphere_radius.max((hi - lo).length() * 0.5);
        self.lod = LodTables::new(&part.nodes, self.center, &self.directory.iteration_table);
        self.leaf_material_count = part.materials.leaf.len();
        self.materials = part.materials;
        self.iteration_radii = part.iteration_radii;
        self.layout = part.layout;
        self.leaf_nodes = part.leaf_nodes;
        self.leaves_offset = part.leaves_offset;
        self.nodes = part.nodes;
        self.opened.extend(part.read);
        self.opened.sort_by_key(|r| r.start);
        self.other_units = self.other_units();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A file whose leaves section has another length than its node table's leaf counts need
    /// (the directory and header CRCs recomputed, so only this check can catch it) is refused at
    /// open with a message; the same file unaltered opens.
    #[tokio::test]
    async fn a_leaves_section_that_disagrees_with_the_node_table_is_refused() {
        use canopy_shared::format::directory::SectionKind;
        use canopy_shared::format::tree::decode_index;
        use canopy_shared::format::{HEADER_LEN, crc32};
        let good = crate::plan::tests::encoded_tree(&[64, 3, 200]);
        let (header, mut dir) = decode_index(&good, Some(good.len() as u64)).expect("index");
        let leaves = dir
            .sections
            .iter_mut()
            .find(|e| e.kind == SectionKind::Leaves)
            .expect("a leaves section");
        leaves.length -= 20;
        let dir_bytes = dir.encode();
        assert_eq!(dir_bytes.len(), header.directory_len as usize);
        let h = canopy_shared::format::header::Header {
            directory_crc: crc32(&dir_bytes),
            ..header
        };
        let mut bad = good.clone();
        bad[..HEADER_LEN].copy_from_slice(&h.encode());
        bad[HEADER_LEN..HEADER_LEN + dir_bytes.len()].copy_from_slice(&dir_bytes);

        let root = std::env::temp_dir().join(format!("canopy-leaves-len-{}", std::process::id()));
        std::fs::create_dir_all(root.join("assets")).expect("mkdir");
        std::fs::write(root.join("assets/good.ctree"), &good).expect("write");
        std::fs::write(root.join("assets/bad.ctree"), &bad).expect("write");
        let src = crate::net::file::FileSource::new(&root);
        let size = good.len() as u64;
        assert!(open_model(&src, "/assets/good.ctree", size).await.is_ok());
        let refused = match open_model(&src, "/assets/bad.ctree", size).await {
            Err(OpenError::Fatal(m)) => m,
            Err(_) => "another error".into(),
            Ok(_) => "opened".into(),
        };
        std::fs::remove_dir_all(&root).ok();
        assert!(refused.contains("leaves section"), "{refused}");
    }
}
