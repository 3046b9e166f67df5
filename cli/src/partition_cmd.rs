//! `dray partition`: cut a scene into domains and write a scene package.
//!
//! The package (see `dray_scene::partition`) is what a cluster loads instead of the
//! scene: a manifest and one file per domain, so each worker reads only its own domains.
//! The command prints one line of JSON so scripts and benchmarks can read the result.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{ArgGroup, Args, ValueEnum};
use dray_core::scene::Scene;
use dray_scene::partition::{LayoutSpec, SceneParts, TriangleSource, WriteOptions, write_package};
use dray_scene::ply_stream::PlySource;
use dray_scene::procedural::ProceduralSource;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum LayoutArg {
    /// A uniform grid over the scene bounds.
    Grid,
    /// A kd split balanced by triangle count.
    Kd,
}

#[derive(Args, Debug)]
#[command(group(ArgGroup::new("count").required(true).args(["domains", "grid"])))]
pub struct PartitionArgs {
    /// A .gltf, .glb, .ply or .obj file, or a procedural scene (cornell, spheres:N,
    /// soup:N, grid:<scene>:XxYxZ, city:N, iso:<field>:<res>).
    pub scene: String,
    /// Number of domains (kd by default; with --layout grid, a grid of exactly N cells
    /// shaped to the scene).
    #[arg(long)]
    pub domains: Option<u32>,
    /// Grid cells per axis, e.g. 4x4x2 (a grid layout).
    #[arg(long, value_name = "XxYxZ")]
    pub grid: Option<String>,
    /// Layout kind (default: grid with --grid, kd with --domains).
    #[arg(long, value_enum)]
    pub layout: Option<LayoutArg>,
    /// Directory to write the package to (created; an existing package there is replaced).
    #[arg(long)]
    pub out: PathBuf,
}

/// The layout the flags ask for.
pub fn layout_spec(a: &PartitionArgs) -> Result<LayoutSpec> {
    let spec = match (a.domains, a.grid.as_deref(), a.layout) {
        (_, Some(_), Some(LayoutArg::Kd)) => {
            bail!("--grid makes a grid layout; for kd use --domains N --layout kd")
        }
        (Some(_), Some(_), _) => bail!("give either --domains or --grid, not both"),
        (_, Some(g), _) => LayoutSpec::parse_grid(g).map_err(|e| anyhow::anyhow!("--grid: {e}"))?,
        (Some(n), None, Some(LayoutArg::Grid)) => LayoutSpec::GridCount(n),
        (Some(n), None, _) => LayoutSpec::Kd(n),
        (None, None, _) => bail!("give --domains N or --grid XxYxZ"),
    };
    spec.check()
        .map_err(|e| anyhow::anyhow!("--domains: {e}"))?;
    Ok(spec)
}

/// Where the triangles come from.
enum Input {
    Procedural(ProceduralSource),
    Ply(PlySource),
    Scene(Scene),
}

/// An existing `.ply` file (a missing one goes to [`dray_scene::load`], whose error
/// explains procedural names too).
fn is_ply_file(spec: &str) -> bool {
    let path = Path::new(spec);
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("ply"))
        && path.is_file()
}

pub fn run(a: PartitionArgs) -> Result<()> {
    let start = Instant::now();
    let spec = layout_spec(&a)?;
    let cannot_load = || format!("cannot load scene {:?}", a.scene);
    // Procedural scenes that can be large (grid, soup, city, iso) and PLY files are
    // streamed, so only a grid's base model, one generator chunk or a PLY's vertex
    // attributes are ever in memory; other files are loaded whole.
    let input = match dray_scene::procedural::stream(&a.scene, &dray_scene::load)
        .with_context(cannot_load)?
    {
        Some(g) => Input::Procedural(g),
        None if is_ply_file(&a.scene) => {
            Input::Ply(PlySource::open(Path::new(&a.scene)).with_context(cannot_load)?)
        }
        None => Input::Scene(dray_scene::load(&a.scene).with_context(cannot_load)?),
    };
    let (tables, source): (&Scene, &dyn TriangleSource) = match &input {
        Input::Procedural(g) => (g.tables(), g),
        Input::Ply(p) => (p.tables(), p),
        Input::Scene(s) => (s, s),
    };
    for w in &tables.stats.warnings {
        tracing::warn!("{w}");
    }
    let load_seconds = start.elapsed().as_secs_f64();
    let written = write_package(
        &a.out,
        SceneParts::of(tables),
        source,
        &spec,
        &WriteOptions::default(),
    );
    let s = written
        .with_context(|| format!("cannot write the scene package to {}", a.out.display()))?;
    let line = serde_json::json!({
        "package": a.out.display().to_string(),
        "layout": s.layout,
        "domains": s.domains,
        "triangles": s.source_triangles,
        "assigned_triangles": s.assigned_triangles,
        "duplicated_share": s.duplicated_share(),
        "min_domain_triangles": s.min_domain_triangles,
        "max_domain_triangles": s.max_domain_triangles,
        "bytes": s.bytes,
        "load_seconds": load_seconds,
        "partition_seconds": s.seconds,
        "seconds": start.elapsed().as_secs_f64(),
    });
    println!("{line}");
    Ok(())
}
