//! `canopy`: the Canopy client. At this stage it opens a `.ctree` the way a streaming client does
//! (header and directory first, then the node table) and prints the byte ranges a uniform
//! simplification rate needs.

use std::path::PathBuf;

use anyhow::{Context, Result};
use canopy_shared::format::directory::SectionKind;
use canopy_shared::format::leaf::keep_count;
use canopy_shared::reader::{FileReader, open_tree};
use clap::{Parser, Subcommand};
use serde_json::json;

/// Canopy client: streams trees by byte range with level of detail.
#[derive(Parser, Debug)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Print the byte ranges of a .ctree that a client at a uniform simplification rate fetches.
    Plan {
        /// The .ctree file.
        file: PathBuf,
        /// Simplification rate in [0, 1]: 0 draws every leaf, 0.9 the first 10 % of each node.
        #[arg(long, default_value_t = 0.5)]
        rate: f32,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
}

fn main() -> Result<()> {
    match Cli::parse().command {
        Command::Plan { file, rate, json } => {
            let reader = FileReader::open(&file).with_context(|| format!("opening {}", file.display()))?;
            let idx = open_tree(&reader).with_context(|| format!("reading {}", file.display()))?;
            let leaves = idx
                .directory
                .section(SectionKind::Leaves)
                .context("no leaves section")?;
            // A uniform rate needs the same number of bands in every node: the most any node needs.
            let counts = idx.layout.leaf_counts();
            let bands = counts
                .iter()
                .map(|&n| idx.layout.bands_for_keep(n, keep_count(n, rate)))
                .max()
                .unwrap_or(0);
            let drawn: u64 = counts.iter().map(|&n| u64::from(keep_count(n, rate))).sum();
            let fetched: u64 = counts
                .iter()
                .map(|&n| u64::from(idx.layout.leaves_in_bands(n, bands)))
                .sum();
            let range = if bands == 0 {
                None
            } else {
                let r = idx.layout.band_range(0).start..idx.layout.band_range(bands - 1).end;
                Some((leaves.offset + r.start, leaves.offset + r.end))
            };
            let report = json!({
                "file": file.display().to_string(),
                "rate": rate,
                "index_bytes": idx.bytes_read,
                "bands": bands,
                "leaves_drawn": drawn,
                "leaves_fetched": fetched,
                "leaf_range": range.map(|(a, b)| json!({"start": a, "end": b, "bytes": b - a})),
                "file_bytes": idx.header.file_len,
            });
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                println!("{report:#}");
            }
            Ok(())
        }
    }
}
