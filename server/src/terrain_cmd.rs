//! `canopy-server terrain generate|import|inspect`: the command line of
//! [`canopy_server::terrain`] (a generated DEM-like terrain, an imported heightmap, a `.cterrain`
//! file's structure). Heights in metres, coordinates `x, z` in metres.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use canopy_server::terrain::generate::{DEMO_CELL_M, DEMO_RELIEF_M};
use canopy_server::terrain::import::{HeightmapFormat, ImportOptions};
use canopy_server::terrain::{generate, import};
use canopy_shared::terrain::{Heightfield, decode_tables};
use serde_json::json;

/// Terrains: generate one, import a heightmap, inspect a file.
#[derive(Debug, clap::Args)]
pub struct TerrainArgs {
    #[command(subcommand)]
    command: TerrainCommand,
}

#[derive(Debug, clap::Subcommand)]
enum TerrainCommand {
    /// Generate a DEM-like terrain (domain-warped fractal noise with ridges), fixed by its seed.
    Generate {
        /// Area: min x, min z, max x, max z, metres (the demo's: -550,-500,550,500).
        #[arg(long, allow_hyphen_values = true, default_value = "-550,-500,550,500")]
        bounds: String,
        /// Sample spacing, metres.
        #[arg(long, default_value_t = DEMO_CELL_M)]
        cell: f64,
        /// Height between the lowest valley and the highest ridge, metres.
        #[arg(long, default_value_t = DEMO_RELIEF_M)]
        relief: f32,
        /// Seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Output `.cterrain` file.
        #[arg(short, long)]
        out: PathBuf,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// Import a heightmap: a 16-bit grayscale PNG or a single-band GeoTIFF (u16, i16 or f32).
    Import {
        /// The heightmap (.png, .tif; told apart by its first bytes).
        heightmap: PathBuf,
        /// Sample spacing, metres (a GeoTIFF's ModelPixelScaleTag otherwise).
        #[arg(long)]
        cell: Option<f64>,
        /// Metres of the 16-bit values 0 and 65535, MIN:MAX (required for a PNG).
        #[arg(long, allow_hyphen_values = true)]
        heights: Option<String>,
        /// Position of the first sample, X,Z (a GeoTIFF's ModelTiepointTag, else centred on 0,0).
        #[arg(long, allow_hyphen_values = true)]
        origin: Option<String>,
        /// Refuse a heightmap of another size than NX,NZ samples.
        #[arg(long)]
        samples: Option<String>,
        /// Output `.cterrain` file.
        #[arg(short, long)]
        out: PathBuf,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// Decode and check a `.cterrain` file and print its grid, tiles, heights and bytes.
    Inspect {
        /// The `.cterrain` file.
        file: PathBuf,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
}

pub fn run(a: &TerrainArgs) -> Result<()> {
    match &a.command {
        TerrainCommand::Generate {
            bounds,
            cell,
            relief,
            seed,
            out,
            json,
        } => {
            let v: Vec<f64> = bounds
                .split(',')
                .map(|x| x.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .with_context(|| format!("--bounds {bounds:?}: four numbers X0,Z0,X1,Z1"))?;
            let &[x0, z0, x1, z1] = v.as_slice() else {
                bail!("--bounds {bounds:?}: four numbers X0,Z0,X1,Z1, not {}", v.len());
            };
            let t0 = std::time::Instant::now();
            let field = generate([x0, z0, x1, z1], *cell, *relief, *seed).context("generating the terrain")?;
            let extra = json!({"seed": seed, "relief_m": relief, "seconds": t0.elapsed().as_secs_f64()});
            write(&field, out, *json, extra)
        }
        TerrainCommand::Import {
            heightmap,
            cell,
            heights,
            origin,
            samples,
            out,
            json,
        } => {
            let mut opts = ImportOptions {
                cell: *cell,
                ..ImportOptions::default()
            };
            for (name, value) in [("heights", heights), ("origin", origin), ("samples", samples)] {
                if let Some(v) = value {
                    opts.set(name, v)
                        .map_err(anyhow::Error::msg)
                        .with_context(|| format!("--{name}"))?;
                }
            }
            let bytes = std::fs::read(heightmap).with_context(|| format!("reading {}", heightmap.display()))?;
            let got = import(&bytes, &opts).with_context(|| format!("importing {}", heightmap.display()))?;
            let format = match got.format {
                HeightmapFormat::Png => "png",
                HeightmapFormat::Tiff => "tiff",
            };
            let extra =
                json!({"source": heightmap, "format": format, "sample": got.sample, "filled_no_data": got.filled});
            write(&got.field, out, *json, extra)
        }
        TerrainCommand::Inspect { file, json } => {
            let bytes = std::fs::read(file).with_context(|| format!("reading {}", file.display()))?;
            let field = Heightfield::decode(&bytes).with_context(|| format!("decoding {}", file.display()))?;
            report(&field, &bytes, file, *json, json!({}))
        }
    }
}

fn write(field: &Heightfield, out: &Path, json_out: bool, extra: serde_json::Value) -> Result<()> {
    let bytes = field.encode();
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    std::fs::write(out, &bytes).with_context(|| format!("writing {}", out.display()))?;
    report(field, &bytes, out, json_out, extra)
}

/// Prints the grid, tiles, heights and bytes.
fn report(field: &Heightfield, bytes: &[u8], path: &Path, json_out: bool, extra: serde_json::Value) -> Result<()> {
    let (grid, tiles) = decode_tables(bytes).context("reading the tables back")?;
    let lo = tiles.iter().map(|t| t.min_height).fold(f32::INFINITY, f32::min);
    let hi = tiles.iter().map(|t| t.max_height).fold(f32::NEG_INFINITY, f32::max);
    let [tx, tz] = grid.tiles();
    let tables = canopy_shared::terrain::tables_len(tiles.len());
    if json_out {
        let mut v = json!({
            "file": path,
            "grid": grid,
            "bounds": grid.bounds(),
            "tiles": {"x": tx, "z": tz, "count": tiles.len()},
            "min_height_m": lo,
            "max_height_m": hi,
            "bytes": bytes.len(),
            "tables_bytes": tables,
            "samples_bytes": bytes.len() as u64 - tables,
        });
        if let (Some(v), serde_json::Value::Object(e)) = (v.as_object_mut(), extra) {
            v.extend(e);
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    let [nx, nz] = grid.samples;
    let b = grid.bounds();
    println!("{}", path.display());
    println!(
        "  grid      {nx} × {nz} samples, cell {} m, origin ({}, {})",
        grid.cell, grid.origin[0], grid.origin[1]
    );
    println!("  covers    [{}, {}]..[{}, {}] (x, z)", b[0], b[1], b[2], b[3]);
    println!(
        "  tiles     {tx} × {tz} = {} of {} cells a side",
        tiles.len(),
        grid.tile_cells
    );
    println!(
        "  heights   {lo:.2} to {hi:.2} m (relief {:.2} m, step {:.4} m)",
        hi - lo,
        grid.height_step
    );
    println!(
        "  bytes     {} ({} header and tile table, {} samples)",
        bytes.len(),
        tables,
        bytes.len() as u64 - tables
    );
    if let serde_json::Value::Object(e) = extra {
        for (k, v) in e {
            println!("  {k:<9} {v}");
        }
    }
    debug_assert_eq!(field.grid, grid);
    Ok(())
}
