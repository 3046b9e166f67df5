//! [`ProceduralSource`]: whichever streaming form a procedural spec has, behind one type,
//! so `dray partition` hands any of them to the package writer the same way.

use dray_core::scene::Scene;

use super::GeneratedSource;
use super::grid::GridSource;
use crate::error::Result;
use crate::partition::{SourceTriangle, TriangleLookup, TriangleSource};

/// A procedural scene as a stream (see [`stream`](super::stream)).
pub enum ProceduralSource {
    /// `grid:SPEC:XxYxZ`: the base scene in memory once, copies made as they are read.
    Grid(GridSource),
    /// `soup:`, `city:`, `iso:`: the generator re-run on every read.
    Generated(GeneratedSource),
}

impl ProceduralSource {
    /// The scene without its triangles: what the package manifest stores.
    pub fn tables(&self) -> &Scene {
        match self {
            ProceduralSource::Grid(g) => g.tables(),
            ProceduralSource::Generated(g) => g.tables(),
        }
    }
}

impl TriangleSource for ProceduralSource {
    fn for_each_triangle(&self, f: &mut dyn FnMut(&SourceTriangle) -> Result<()>) -> Result<()> {
        match self {
            ProceduralSource::Grid(g) => g.for_each_triangle(f),
            ProceduralSource::Generated(g) => g.for_each_triangle(f),
        }
    }

    fn has_colors(&self) -> bool {
        match self {
            ProceduralSource::Grid(g) => g.has_colors(),
            ProceduralSource::Generated(g) => g.has_colors(),
        }
    }

    fn lookup(&self) -> Option<&dyn TriangleLookup> {
        match self {
            ProceduralSource::Grid(g) => g.lookup(),
            ProceduralSource::Generated(g) => g.lookup(),
        }
    }
}
