//! `dray coordinator`: serve the public `dray.v1.RenderService` (with gRPC reflection and
//! health) on `--listen`.
//!
//! Workers are not wired yet: accepted jobs render in this process, one at a time, with
//! the same code path as `dray render`, so an image fetched with GetImage has the same
//! bits as `dray render` with the same settings.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;

#[derive(Args, Debug)]
pub struct CoordinatorArgs {
    /// Address to serve gRPC on, e.g. 127.0.0.1:7070 (port 0 picks a free port).
    #[arg(long)]
    pub listen: String,
    /// Directory that scene files in jobs are resolved against; paths escaping it are
    /// rejected. Procedural scenes (cornell, spheres:N, ...) need no files.
    #[arg(long, default_value = ".")]
    pub scene_root: PathBuf,
    /// Render threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
}

pub fn run(a: CoordinatorArgs) -> Result<()> {
    let coordinator = dray_coordinator::Coordinator::new(&a.scene_root, a.threads)
        .with_context(|| format!("--scene-root {}", a.scene_root.display()))?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    rt.block_on(async {
        let listener = tokio::net::TcpListener::bind(&a.listen)
            .await
            .with_context(|| format!("cannot listen on {}", a.listen))?;
        let addr = listener
            .local_addr()
            .context("cannot read the bound address")?;
        // One line on stdout, so scripts and tests can find the port.
        println!("dray coordinator listening on {addr}");
        eprintln!(
            "scene root {} (workers are not wired yet: jobs render in this process)",
            coordinator.scene_root().display()
        );
        dray_coordinator::serve(listener, coordinator, std::future::pending())
            .await
            .context("the gRPC server stopped")
    })
}
