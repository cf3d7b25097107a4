//! `canopy load`: simulated viewers against a server (not built yet).

use anyhow::{Result, bail};
use clap::Args;

use crate::cli::SceneArgs;

/// Options of `canopy load`.
#[derive(Args, Debug)]
pub struct LoadArgs {
    #[command(flatten)]
    pub scene: SceneArgs,
}

/// Runs the load test.
pub async fn run(a: LoadArgs) -> Result<()> {
    let _ = a;
    bail!("canopy load is not built yet")
}
