//! `canopy-server inspect`: a `.ctree` file's structure (leaves, nodes, levels, sections, cloud
//! levels, atlas images and their byte ranges) as text or JSON.

use std::path::Path;

use anyhow::{Context, Result};
use canopy_shared::format::NodeKind;
use canopy_shared::format::directory::SectionKind;
use serde_json::json;

use super::read_tree;

/// Prints the structure of `file`.
pub fn run(file: &Path, json_out: bool) -> Result<()> {
    let (bytes, t) = read_tree(file)?;
    let d = &t.directory;
    let mut levels = std::collections::BTreeMap::<u8, (u32, u32)>::new();
    for n in &t.nodes {
        let e = levels.entry(n.branch_level).or_default();
        match n.kind {
            NodeKind::Branch => e.0 += 1,
            NodeKind::Leaf => e.1 += 1,
        }
    }
    let mut branch_levels = std::collections::BTreeMap::<u8, u32>::new();
    for b in &t.branches {
        *branch_levels.entry(b.level).or_default() += 1;
    }
    let sizes: Vec<usize> = t.node_leaves.iter().map(Vec::len).collect();
    let sections: Vec<_> = SectionKind::ALL
        .iter()
        .filter_map(|k| d.section(*k))
        .map(|s| json!({"kind": s.kind.name(), "offset": s.offset, "bytes": s.length, "items": s.item_count}))
        .collect();
    let dir_len = t.header.directory_len;
    let clouds = match d.section(SectionKind::BillboardClouds) {
        Some(e) => {
            let sec = canopy_shared::format::tree::section_bytes(&bytes, e)?;
            let ct = canopy_shared::format::cloud::decode_clouds(sec)
                .with_context(|| format!("decoding the billboard clouds of {}", file.display()))?;
            Some(ct)
        }
        None => None,
    };
    // A bake without atlases leaves the section empty.
    let atlas = match d.section(SectionKind::BillboardAtlases).filter(|e| e.length > 0) {
        Some(e) => {
            let sec = canopy_shared::format::tree::section_bytes(&bytes, e)?;
            let at = canopy_shared::format::atlas::AtlasTable::decode(sec, e.length)
                .with_context(|| format!("decoding the billboard atlases of {}", file.display()))?;
            Some((e.offset, at))
        }
        None => None,
    };
    // Every image with its file range, so that a fetch log can be read image by image.
    let atlas_json = atlas.as_ref().map(|(base, at)| {
        json!({
            "resolutions": at.resolutions,
            "frames": at.frames.len(),
            "layouts": at.layouts.iter().map(|l| json!({
                "layout": l.kind.name(),
                "first_frame": l.first_frame,
                "frames": l.frame_count(),
            })).collect::<Vec<_>>(),
            "images": at.frames.iter().enumerate().flat_map(|(f, fr)| {
                fr.images.iter().enumerate().filter(|(_, im)| im.length > 0).map(move |(r, im)| json!({
                    "frame": f,
                    "resolution": r,
                    "range": [base + u64::from(im.offset), base + u64::from(im.offset) + u64::from(im.length)],
                }))
            }).collect::<Vec<_>>(),
        })
    });
    let clouds_json = clouds.as_ref().map(|ct| {
        json!({
            "flags": ct.flags,
            "texture_density": ct.flags & canopy_shared::format::cloud::CLOUD_FLAG_TEXTURE_DENSITY != 0,
            "view_line_height": (ct.view_line_height > 0.0).then_some(ct.view_line_height),
            "radius": ct.radius,
            "table_bytes": canopy_shared::format::cloud::CloudTable::table_len(ct.levels.len(), ct.planes.len()),
            "levels": ct.levels.iter().enumerate().map(|(k, l)| json!({
                "level": k + 1,
                "epsilon": l.epsilon,
                "texel": l.texel,
                "planes": l.plane_count,
                "texture_bytes": l.textures.length,
                "range": [l.textures.offset, l.textures.offset + l.textures.length],
                "texels": ct.level_planes(k).iter().map(|p| u64::from(p.width) * u64::from(p.height)).sum::<u64>(),
            })).collect::<Vec<_>>(),
        })
    });
    let report = json!({
        "file": file.display().to_string(),
        "name": d.name,
        "version": format!("{}.{}", t.header.version_major, t.header.version_minor),
        "source": format!("{:?}", d.source),
        "leaf_order": d.leaf_order.name(),
        "iterations": d.iterations,
        "iteration_table": d.iteration_table.iter().enumerate().map(|(k, e)| json!({
            "iteration": k,
            "branches_end": e.branches_end,
            "skeleton_bytes_end": e.skeleton_bytes_end,
            "leaves_end": e.leaves_end,
            "leaf_nodes": t.nodes.iter().filter(|n| n.kind == canopy_shared::format::NodeKind::Leaf
                && n.branch != canopy_shared::format::NO_BRANCH
                && canopy_shared::format::branch_iteration(&d.iteration_table, n.branch) == Some(k as u8)).count(),
        })).collect::<Vec<_>>(),
        "file_bytes": bytes.len(),
        "header_bytes": canopy_shared::format::HEADER_LEN,
        "directory_bytes": dir_len,
        "first_request_bytes": canopy_shared::format::HEADER_LEN as u32 + dir_len,
        "leaves": d.leaf_count,
        "branches": d.branch_count,
        "nodes": d.node_count,
        "leaf_nodes": d.leaf_node_count,
        "leaves_per_leaf_node": { "min": sizes.iter().min(), "max": sizes.iter().max(), "mean": if sizes.is_empty() { 0.0 } else { d.leaf_count as f64 / sizes.len() as f64 } },
        "nodes_by_level": levels.iter().map(|(l, (b, lf))| json!({"level": l, "branch_nodes": b, "leaf_nodes": lf})).collect::<Vec<_>>(),
        "branches_by_level": branch_levels.iter().map(|(l, n)| json!({"level": l, "branches": n})).collect::<Vec<_>>(),
        "band_edges": d.band_edges.iter().map(|&e| f64::from(e) / 65535.0).collect::<Vec<_>>(),
        "bounds": { "min": d.bounds_min.to_array(), "max": d.bounds_max.to_array() },
        "sections": sections,
        "clouds": clouds_json,
        "atlas": atlas_json,
    });
    if json_out {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!(
        "{} ({}), format {}.{}, leaf order {}",
        d.name,
        file.display(),
        t.header.version_major,
        t.header.version_minor,
        d.leaf_order.name()
    );
    println!(
        "  {} leaves, {} branches, {} nodes ({} leaf nodes), {} iterations",
        d.leaf_count, d.branch_count, d.node_count, d.leaf_node_count, d.iterations
    );
    println!(
        "  height {:.2} m, header + directory {} bytes",
        d.bounds_max.y - d.bounds_min.y,
        64 + dir_len
    );
    for (l, (b, lf)) in &levels {
        println!("  level {l}: {b} branch nodes, {lf} leaf nodes");
    }
    for s in SectionKind::ALL.iter().filter_map(|k| d.section(*k)) {
        println!(
            "  {:<18} {:>10} bytes  {:>8} items",
            s.kind.name(),
            s.length,
            s.item_count
        );
    }
    if let Some(ct) = &clouds {
        for (k, l) in ct.levels.iter().enumerate() {
            println!(
                "  cloud level {}: ε {:.2} m, {} planes, {} texture bytes",
                k + 1,
                l.epsilon,
                l.plane_count,
                l.textures.length
            );
        }
    }
    println!("  total {} bytes", bytes.len());
    Ok(())
}
