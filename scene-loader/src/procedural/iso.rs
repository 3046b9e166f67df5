//! `iso:FIELD:RES`: marching-cubes isosurfaces of analytic fields.
//!
//! Smooth, closed, arbitrarily fine meshes with exact normals: the surface `f = 0` of a
//! field sampled at the corners of a RES^3 cell grid over the field's domain (`f < 0` is
//! inside). Closed fields (sphere, torus, metaballs, heart) stay strictly inside their
//! domain, so their meshes are watertight 2-manifolds; the gyroid is cut open by the box.
//!
//! Watertightness needs two things, both enforced here:
//! - every grid edge gets exactly one vertex, shared by the (up to four) cells around it:
//!   vertex indices are cached per edge in per-slab arrays, so neighbouring cells reuse
//!   the same index rather than an equal position;
//! - neighbouring cells must cut their shared face the same way. The triangle table uses
//!   the classic Lorensen/Bourke corner and edge numbering (256 cases, at most 5
//!   triangles, `-1`-terminated) but is derived at compile time from one rule: on every
//!   face, inside corners (bit set) that are not joined by a face edge are kept apart.
//!   Since the choice depends only on the face's four corners, the two cells sharing a
//!   face always agree, which rules out the cracks of tables built by complement symmetry;
//!   and triangulation diagonals never lie in a face, so no edge gets a third triangle
//!   from the neighbour. A test runs random sign fields (every case, every ambiguity)
//!   and checks the result is closed and consistently oriented.
//!
//! Vertex normals are the normalised field gradient (central differences), so shading is
//! smooth and independent of the triangulation.

use dray_core::camera::Camera;
use dray_core::light::Light;
use dray_core::material::Material;
use dray_core::scene::Scene;
use glam::{DVec3, Vec3};

use super::{Builder, Generator, MAX_TRIANGLES, Rng, Sink, frame, parse_count, spec_error};
use crate::error::Result;

const DEFAULT_FIELD: &str = "sphere";
const DEFAULT_RES: &str = "64";
/// 2048^3 cells is 8.6 G field samples: minutes of work per pass and tens of millions of
/// triangles. Streaming keeps memory bounded at any size; the cap bounds the time.
const MAX_RES: u64 = 2048;
/// Two cells per axis is the smallest grid with an interior sample.
const MIN_RES: u64 = 2;
const SEED: u64 = 0x5EED_5EED_0000_0004;
/// Interpolation parameters are kept this far from the edge ends, so a sample that lies
/// exactly on the surface cannot make two vertices coincide (which would create
/// zero-area triangles that validation drops, opening a hole).
const T_MARGIN: f64 = 1e-3;

/// Offsets of the cell corners, Lorensen/Bourke numbering: 0-3 counter-clockwise around
/// the z = 0 face, 4-7 above them.
const CORNERS: [[usize; 3]; 8] = [
    [0, 0, 0],
    [1, 0, 0],
    [1, 1, 0],
    [0, 1, 0],
    [0, 0, 1],
    [1, 0, 1],
    [1, 1, 1],
    [0, 1, 1],
];

/// The corners each edge joins, Lorensen/Bourke numbering.
const EDGES: [[usize; 2]; 12] = [
    [0, 1],
    [1, 2],
    [2, 3],
    [3, 0],
    [4, 5],
    [5, 6],
    [6, 7],
    [7, 4],
    [0, 4],
    [1, 5],
    [2, 6],
    [3, 7],
];

/// The cell's faces, corners counter-clockwise seen from outside the cell.
const FACES: [[usize; 4]; 6] = [
    [0, 3, 2, 1],
    [4, 5, 6, 7],
    [0, 1, 5, 4],
    [3, 7, 6, 2],
    [0, 4, 7, 3],
    [1, 2, 6, 5],
];

const fn edge_between(a: usize, b: usize) -> usize {
    let mut e = 0;
    while e < 12 {
        let [p, q] = EDGES[e];
        if (p == a && q == b) || (p == b && q == a) {
            return e;
        }
        e += 1;
    }
    panic!("marching cubes: corners are not joined by an edge")
}

/// True when cube edges `a` and `b` lie on a common face (or are the same edge).
const fn shares_face(a: usize, b: usize) -> bool {
    let mut f = 0;
    while f < 6 {
        let mut hits = 0;
        let mut k = 0;
        while k < 4 {
            let e = edge_between(FACES[f][k], FACES[f][(k + 1) % 4]);
            if e == a || e == b {
                hits += 1;
            }
            k += 1;
        }
        if hits == 2 || (a == b && hits == 1) {
            return true;
        }
        f += 1;
    }
    false
}

const fn inside(case: usize, corner: usize) -> bool {
    case & (1 << corner) != 0
}

/// For each case (bit c set when corner c is inside), the edges the surface crosses.
pub(crate) const EDGE_TABLE: [u16; 256] = {
    let mut table = [0u16; 256];
    let mut case = 0;
    while case < 256 {
        let mut e = 0;
        while e < 12 {
            if inside(case, EDGES[e][0]) != inside(case, EDGES[e][1]) {
                table[case] |= 1 << e;
            }
            e += 1;
        }
        case += 1;
    }
    table
};

/// For each case, up to five triangles as edge triples, `-1`-terminated, wound
/// counter-clockwise seen from outside (so geometric normals point along the gradient).
///
/// Derivation: on each face, walking its corners counter-clockwise, every run of inside
/// corners is cut off by a segment from the edge where the run starts to the edge where
/// it ends. Each crossed edge lies on two faces, starting a segment on one and ending one
/// on the other, so the segments link into closed loops. Each loop is triangulated by
/// clipping ears whose new diagonal runs through the cell's interior, never along a face
/// (where the neighbouring cell could draw the same edge). Any inconsistency fails the
/// build, not a render.
pub(crate) const TRI_TABLE: [[i8; 16]; 256] = {
    const NONE: usize = usize::MAX;
    let mut table = [[-1i8; 16]; 256];
    let mut case = 0;
    while case < 256 {
        let mut next = [NONE; 12];
        let mut f = 0;
        while f < 6 {
            let face = FACES[f];
            let mut k = 0;
            while k < 4 {
                let prev = face[(k + 3) % 4];
                if inside(case, face[k]) && !inside(case, prev) {
                    let mut last = k;
                    while inside(case, face[(last + 1) % 4]) {
                        last = (last + 1) % 4;
                    }
                    let entry = edge_between(prev, face[k]);
                    let exit = edge_between(face[last], face[(last + 1) % 4]);
                    if next[entry] != NONE {
                        panic!("marching cubes: edge starts two segments");
                    }
                    next[entry] = exit;
                }
                k += 1;
            }
            f += 1;
        }
        let mut visited = [false; 12];
        let mut out = 0;
        let mut start = 0;
        while start < 12 {
            if next[start] != NONE && !visited[start] {
                let mut ring = [0usize; 12];
                let mut len = 0;
                let mut cur = start;
                loop {
                    if cur == NONE || visited[cur] {
                        panic!("marching cubes: segments do not form a loop");
                    }
                    visited[cur] = true;
                    ring[len] = cur;
                    len += 1;
                    cur = next[cur];
                    if cur == start {
                        break;
                    }
                }
                // Clip ears whose closing diagonal crosses the cell's interior: a
                // diagonal between two edges of one face would lie in that face, where
                // the neighbouring cell may draw the same diagonal (four triangles on
                // one edge). Ring edges are the face segments and are always fine.
                while len >= 3 {
                    // The last triangle keeps the ring's order (ear 1), so a lone
                    // triangle reads like the classic table.
                    let mut ear = 1;
                    if len > 3 {
                        ear = 0;
                        while ear < len
                            && shares_face(ring[(ear + len - 1) % len], ring[(ear + 1) % len])
                        {
                            ear += 1;
                        }
                        if ear == len {
                            panic!("marching cubes: no interior triangulation of a loop");
                        }
                    }
                    if out + 3 >= 16 {
                        panic!("marching cubes: more than five triangles in a case");
                    }
                    table[case][out] = ring[(ear + len - 1) % len] as i8;
                    table[case][out + 1] = ring[ear] as i8;
                    table[case][out + 2] = ring[(ear + 1) % len] as i8;
                    out += 3;
                    let mut m = ear;
                    while m + 1 < len {
                        ring[m] = ring[m + 1];
                        m += 1;
                    }
                    len -= 1;
                    if len < 3 {
                        break;
                    }
                }
            }
            start += 1;
        }
        case += 1;
    }
    table
};

/// An analytic field; the surface is `value = 0`, negative inside.
enum Field {
    Sphere,
    Torus,
    Gyroid,
    /// Compactly supported blobs `(centre, support radius)`; the polynomial falloff
    /// reaches exactly zero at the support radius, so the surface cannot leak to the
    /// domain boundary the way 1/r^2 metaballs do.
    Metaballs(Vec<(DVec3, f64)>),
    Heart,
}

const FIELDS: &str = "sphere, torus, gyroid, metaballs, heart";
/// The metaball iso threshold: a lone ball's surface sits at 0.64 of its support radius.
const METABALL_THRESHOLD: f64 = 0.2;

impl Field {
    fn parse(name: &str) -> Option<Field> {
        Some(match name {
            "sphere" => Field::Sphere,
            "torus" => Field::Torus,
            "gyroid" => Field::Gyroid,
            "metaballs" => {
                let mut rng = Rng::new(SEED);
                Field::Metaballs(
                    (0..7)
                        .map(|_| {
                            let c = DVec3::new(
                                rng.range(-0.45, 0.45) as f64,
                                rng.range(-0.45, 0.45) as f64,
                                rng.range(-0.45, 0.45) as f64,
                            );
                            (c, rng.range(0.3, 0.5) as f64)
                        })
                        .collect(),
                )
            }
            "heart" => Field::Heart,
            _ => return None,
        })
    }

    /// The sampled box. Closed fields stay strictly inside it.
    fn domain(&self) -> (DVec3, DVec3) {
        match self {
            Field::Heart => (DVec3::splat(-1.5), DVec3::splat(1.5)),
            _ => (DVec3::splat(-1.0), DVec3::splat(1.0)),
        }
    }

    fn value(&self, p: DVec3) -> f64 {
        match self {
            Field::Sphere => p.length() - 0.8,
            Field::Torus => {
                let ring = (p.x * p.x + p.z * p.z).sqrt() - 0.6;
                (ring * ring + p.y * p.y).sqrt() - 0.25
            }
            Field::Gyroid => {
                // Two periods across the box.
                let q = p * std::f64::consts::TAU;
                q.x.sin() * q.y.cos() + q.y.sin() * q.z.cos() + q.z.sin() * q.x.cos()
            }
            Field::Metaballs(balls) => {
                let sum: f64 = balls
                    .iter()
                    .map(|&(c, r)| {
                        let s = 1.0 - (p - c).length_squared() / (r * r);
                        if s > 0.0 { s * s * s } else { 0.0 }
                    })
                    .sum();
                METABALL_THRESHOLD - sum
            }
            Field::Heart => {
                // Taubin's heart surface, its z axis turned to our Y.
                let (x, y, z) = (p.x, p.z, p.y);
                let a = x * x + 2.25 * y * y + z * z - 1.0;
                a * a * a - x * x * z * z * z - 0.1125 * y * y * z * z * z
            }
        }
    }

    fn albedo(&self) -> Vec3 {
        match self {
            Field::Sphere => Vec3::splat(0.75),
            Field::Torus => Vec3::new(0.8, 0.6, 0.25),
            Field::Gyroid => Vec3::new(0.2, 0.55, 0.6),
            Field::Metaballs(_) => Vec3::new(0.85, 0.45, 0.2),
            Field::Heart => Vec3::new(0.75, 0.1, 0.15),
        }
    }
}

/// The mesh being extracted: shared vertices with gradient normals, and triangles whose
/// indices number the vertices over the whole surface.
#[derive(Default)]
struct Surface {
    positions: Vec<Vec3>,
    normals: Vec<Vec3>,
    indices: Vec<u32>,
}

impl Surface {
    fn clear(&mut self) {
        self.positions.clear();
        self.normals.clear();
        self.indices.clear();
    }
}

/// What one slab of cells (between sample layers k and k+1) adds to the surface: the
/// vertices made while extracting it, the first being surface vertex `first_vertex`, and
/// its triangles, indexed over the whole surface. They use only this slab's vertices and
/// the previous slab's: a vertex on the layer two slabs share is made by the lower slab.
struct Slab<'a> {
    first_vertex: u32,
    positions: &'a [Vec3],
    normals: &'a [Vec3],
    indices: &'a [u32],
}

/// Vertex indices of the grid edges around one slab of cells (between sample layers k
/// and k+1); `u32::MAX` marks an edge without a vertex yet. `x`/`y` arrays hold the edges
/// lying in a layer, `z` the edges joining the two layers.
struct SlabEdges {
    x_lo: Vec<u32>,
    y_lo: Vec<u32>,
    x_hi: Vec<u32>,
    y_hi: Vec<u32>,
    z: Vec<u32>,
    /// Cells per axis.
    res: usize,
}

const NO_VERTEX: u32 = u32::MAX;

impl SlabEdges {
    fn new(res: usize) -> Self {
        let n = res + 1;
        SlabEdges {
            x_lo: vec![NO_VERTEX; res * n],
            y_lo: vec![NO_VERTEX; n * res],
            x_hi: vec![NO_VERTEX; res * n],
            y_hi: vec![NO_VERTEX; n * res],
            z: vec![NO_VERTEX; n * n],
            res,
        }
    }

    /// The slot of edge `e` of cell (i, j) in this slab.
    fn slot(&mut self, e: usize, i: usize, j: usize) -> &mut u32 {
        let [a, b] = EDGES[e];
        let (ca, cb) = (CORNERS[a], CORNERS[b]);
        let (x, y, top) = (
            i + ca[0].min(cb[0]),
            j + ca[1].min(cb[1]),
            ca[2].min(cb[2]) == 1,
        );
        let n = self.res + 1;
        if ca[0] != cb[0] {
            let layer = if top { &mut self.x_hi } else { &mut self.x_lo };
            &mut layer[y * self.res + x]
        } else if ca[1] != cb[1] {
            let layer = if top { &mut self.y_hi } else { &mut self.y_lo };
            &mut layer[y * n + x]
        } else {
            &mut self.z[y * n + x]
        }
    }

    /// Move on to the next slab: its bottom layer is this slab's top layer.
    fn advance(&mut self) {
        std::mem::swap(&mut self.x_lo, &mut self.x_hi);
        std::mem::swap(&mut self.y_lo, &mut self.y_hi);
        self.x_hi.fill(NO_VERTEX);
        self.y_hi.fill(NO_VERTEX);
        self.z.fill(NO_VERTEX);
    }
}

/// The gradient of `f` at `p` by central differences of step `h`.
fn gradient(f: &dyn Fn(DVec3) -> f64, p: DVec3, h: f64) -> DVec3 {
    let d = |axis: DVec3| (f(p + axis * h) - f(p - axis * h)) / (2.0 * h);
    DVec3::new(d(DVec3::X), d(DVec3::Y), d(DVec3::Z))
}

/// Run marching cubes over `res^3` cells of the box `lo..hi` for the field `f`, handing
/// the surface to `out` slab by slab, bottom (z = lo) to top; memory is a few layers of
/// samples and one slab of output.
fn extract(
    spec: &str,
    f: &dyn Fn(DVec3) -> f64,
    (lo, hi): (DVec3, DVec3),
    res: usize,
    out: &mut dyn FnMut(Slab<'_>) -> Result<()>,
) -> Result<()> {
    let step = (hi - lo) / res as f64;
    let h = step.min_element() * 0.1;
    let n = res + 1;
    let point = |i: usize, j: usize, k: usize| lo + step * DVec3::new(i as f64, j as f64, k as f64);
    let fill = |layer: &mut Vec<f64>, k: usize| {
        for j in 0..n {
            for i in 0..n {
                layer[j * n + i] = f(point(i, j, k));
            }
        }
    };
    let mut below = vec![0.0; n * n];
    let mut above = vec![0.0; n * n];
    fill(&mut below, 0);
    let mut edges = SlabEdges::new(res);
    let mut slab = Surface::default();
    // Vertices and triangles made so far, over all slabs.
    let mut vertices = 0u64;
    let mut triangles = 0u64;
    for k in 0..res {
        crate::cancel::check()?;
        fill(&mut above, k + 1);
        slab.clear();
        let first_vertex = vertices;
        for j in 0..res {
            for i in 0..res {
                let mut values = [0.0; 8];
                let mut case = 0;
                for (c, v) in values.iter_mut().enumerate() {
                    let [dx, dy, dz] = CORNERS[c];
                    let layer = if dz == 0 { &below } else { &above };
                    *v = layer[(j + dy) * n + i + dx];
                    if *v < 0.0 {
                        case |= 1 << c;
                    }
                }
                let crossed = EDGE_TABLE[case];
                if crossed == 0 {
                    continue;
                }
                let mut vertex = [0u32; 12];
                for (e, slot_out) in vertex.iter_mut().enumerate() {
                    if crossed & (1 << e) == 0 {
                        continue;
                    }
                    let slot = edges.slot(e, i, j);
                    if *slot == NO_VERTEX {
                        if vertices >= NO_VERTEX as u64 {
                            return Err(spec_error(spec, "surface exceeds 4 billion vertices"));
                        }
                        let [a, b] = EDGES[e];
                        let corner = |c: usize| {
                            let [dx, dy, dz] = CORNERS[c];
                            point(i + dx, j + dy, k + dz)
                        };
                        let (va, vb) = (values[a], values[b]);
                        let t = (va / (va - vb)).clamp(T_MARGIN, 1.0 - T_MARGIN);
                        let p = corner(a).lerp(corner(b), t);
                        let g = gradient(f, p, h);
                        slab.positions.push(p.as_vec3());
                        slab.normals.push(g.normalize_or_zero().as_vec3());
                        // Below NO_VERTEX, checked above.
                        *slot = vertices as u32;
                        vertices += 1;
                    }
                    *slot_out = *slot;
                }
                for tri in TRI_TABLE[case].chunks_exact(3) {
                    if tri[0] < 0 {
                        break;
                    }
                    slab.indices.extend(tri.iter().map(|&e| vertex[e as usize]));
                }
            }
        }
        triangles += (slab.indices.len() / 3) as u64;
        if triangles > MAX_TRIANGLES {
            return Err(spec_error(
                spec,
                format!("the surface exceeds the cap of {MAX_TRIANGLES} triangles"),
            ));
        }
        out(Slab {
            // At most NO_VERTEX, checked before every vertex made.
            first_vertex: first_vertex as u32,
            positions: &slab.positions,
            normals: &slab.normals,
            indices: &slab.indices,
        })?;
        std::mem::swap(&mut below, &mut above);
        edges.advance();
    }
    Ok(())
}

/// The whole surface of [`extract`] in memory, every vertex once.
fn extract_surface(
    spec: &str,
    f: &dyn Fn(DVec3) -> f64,
    domain: (DVec3, DVec3),
    res: usize,
) -> Result<Surface> {
    let mut surface = Surface::default();
    extract(spec, f, domain, res, &mut |slab| {
        surface.positions.extend_from_slice(slab.positions);
        surface.normals.extend_from_slice(slab.normals);
        surface.indices.extend_from_slice(slab.indices);
        Ok(())
    })?;
    Ok(surface)
}

/// Streams slabs to a sink as primitives. A slab's triangles may use the previous slab's
/// vertices, so each primitive carries both slabs' vertices, renumbered from the older
/// one: two slabs are all streaming ever holds. The triangles are those of the whole
/// surface in memory: renumbering is one-to-one (so the validation gate's repeated-index
/// test agrees) and positions and normals are the same values.
#[derive(Default)]
struct SlabWindow {
    /// Surface index of the first vertex held.
    start: u32,
    /// Surface index of the latest slab's first vertex.
    latest: u32,
    positions: Vec<Vec3>,
    normals: Vec<Vec3>,
    local: Vec<u32>,
}

impl SlabWindow {
    fn push(
        &mut self,
        spec: &str,
        slab: Slab<'_>,
        material: u32,
        sink: &mut dyn Sink,
    ) -> Result<()> {
        // Forget the vertices of the slab before the previous one.
        let stale = (self.latest - self.start) as usize;
        self.positions.drain(..stale);
        self.normals.drain(..stale);
        self.start = self.latest;
        self.latest = slab.first_vertex;
        self.positions.extend_from_slice(slab.positions);
        self.normals.extend_from_slice(slab.normals);
        if slab.indices.is_empty() {
            return Ok(());
        }
        self.local.clear();
        for &v in slab.indices {
            let Some(l) = v.checked_sub(self.start) else {
                return Err(spec_error(
                    spec,
                    "internal error: a slab uses a vertex older than the previous slab",
                ));
            };
            self.local.push(l);
        }
        sink.add_triangles(&self.positions, Some(&self.normals), &self.local, material)
    }
}

/// `iso:FIELD:RES`, parsed.
pub(super) struct Iso {
    name: String,
    field: Field,
    res: usize,
}

/// The one material; triangles refer to it by this index.
const MATERIAL: u32 = 0;

impl Iso {
    pub(super) fn parse(spec: &str, args: Option<&str>) -> Result<Iso> {
        let (name, res) = match args {
            None => (DEFAULT_FIELD, DEFAULT_RES),
            Some(a) => a.split_once(':').unwrap_or((a, DEFAULT_RES)),
        };
        let field = Field::parse(name).ok_or_else(|| {
            spec_error(
                spec,
                format!("unknown field {name:?} (expected one of {FIELDS})"),
            )
        })?;
        let res = parse_count(spec, "grid resolution", res, MIN_RES, MAX_RES)? as usize;
        Ok(Iso {
            name: name.to_string(),
            field,
            res,
        })
    }
}

impl Generator for Iso {
    fn name(&self) -> &'static str {
        "iso"
    }

    /// A surface crosses about RES^2 cells; measured at RES 64 and 128 the fields make
    /// 3 (metaballs) to 19.6 (gyroid) triangles per RES^2, so 20 RES^2 bounds them all.
    fn triangle_estimate(&self) -> u64 {
        (self.res as u64).pow(2).saturating_mul(20)
    }

    fn tables(&self, spec: &str) -> Scene {
        Scene {
            name: spec.to_string(),
            materials: vec![Material::lambert(
                &format!("iso {}", self.name),
                self.field.albedo(),
            )],
            lights: vec![Light::Directional {
                direction: Vec3::new(-0.4, -1.0, -0.6).normalize(),
                irradiance: Vec3::splat(3.0),
            }],
            environment: Some(Vec3::new(0.12, 0.14, 0.18)),
            ..Scene::default()
        }
    }

    /// Slab by slab, one primitive each (see [`SlabWindow`]).
    fn emit(&self, spec: &str, sink: &mut dyn Sink) -> Result<()> {
        let mut window = SlabWindow::default();
        let f = |p| self.field.value(p);
        extract(spec, &f, self.field.domain(), self.res, &mut |slab| {
            window.push(spec, slab, MATERIAL, sink)
        })
    }

    /// In memory the surface is one primitive, so every vertex is stored once (slab
    /// primitives would store the vertices on each shared layer twice).
    fn build(&self, spec: &str, builder: &mut Builder<'_>) -> Result<()> {
        let f = |p| self.field.value(p);
        let s = extract_surface(spec, &f, self.field.domain(), self.res)?;
        builder.add_triangles(&s.positions, Some(&s.normals), &s.indices, MATERIAL)
    }

    fn cameras(&self, lo: Vec3, hi: Vec3) -> Vec<Camera> {
        vec![frame("iso", lo, hi, Vec3::new(0.55, 0.45, 1.0), 40.0)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tables_match_the_classic_layout() {
        // Empty and full cells have nothing; one corner gives one triangle.
        assert_eq!(EDGE_TABLE[0], 0);
        assert_eq!(EDGE_TABLE[255], 0);
        assert_eq!(EDGE_TABLE[1], 0x109);
        assert_eq!(&TRI_TABLE[1][..4], &[0, 3, 8, -1]);
        for case in 0..256 {
            let used: u16 = TRI_TABLE[case]
                .iter()
                .take_while(|&&e| e >= 0)
                .fold(0, |m, &e| m | 1 << e);
            assert_eq!(used, EDGE_TABLE[case], "case {case}");
            assert!(
                TRI_TABLE[case]
                    .iter()
                    .skip_while(|&&e| e >= 0)
                    .all(|&e| e == -1)
            );
        }
    }

    #[test]
    fn triangles_face_along_the_gradient() {
        for name in ["sphere", "torus", "metaballs", "heart"] {
            let field = Field::parse(name).unwrap();
            let s = extract_surface("t", &|p| field.value(p), field.domain(), 24).unwrap();
            let mut agree = 0;
            for t in s.indices.chunks_exact(3) {
                let [a, b, c] = [0, 1, 2].map(|k| s.positions[t[k] as usize]);
                let n = (b - a).cross(c - a);
                let g =
                    s.normals[t[0] as usize] + s.normals[t[1] as usize] + s.normals[t[2] as usize];
                if n.dot(g) > 0.0 {
                    agree += 1;
                }
            }
            // Heart has singular points where the gradient vanishes; everything else agrees.
            assert!(agree * 100 >= s.indices.len() / 3 * 99, "{name}: {agree}");
        }
    }

    /// Random corner signs hit every case, including all ambiguous faces; with the
    /// boundary forced outside, the surface must still be closed.
    #[test]
    fn random_fields_are_watertight() {
        let res = 14;
        for seed in 0..20 {
            let noise = |p: DVec3| {
                let [i, j, k] = [p.x, p.y, p.z].map(|c| c.round() as i64);
                if [i, j, k].iter().any(|&c| c <= 0 || c >= res as i64) {
                    return 1.0;
                }
                let key = (i * 73_856_093) ^ (j * 19_349_663) ^ (k * 83_492_791) ^ seed;
                Rng::new(key as u64).f32() as f64 - 0.5
            };
            let box_ = (DVec3::ZERO, DVec3::splat(res as f64));
            let s = extract_surface("t", &noise, box_, res).unwrap();
            // Closed and consistently oriented: every directed edge is used exactly once
            // and its reverse exists (so each undirected edge has exactly two triangles).
            let mut directed = std::collections::HashMap::new();
            for t in s.indices.chunks_exact(3) {
                assert!(t[0] != t[1] && t[1] != t[2] && t[0] != t[2]);
                for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                    *directed.entry((a, b)).or_insert(0) += 1;
                }
            }
            assert!(directed.len() > 1000);
            for (&(a, b), &uses) in &directed {
                assert_eq!(uses, 1, "seed {seed}: edge {a}-{b} used {uses} times");
                assert!(
                    directed.contains_key(&(b, a)),
                    "seed {seed}: open edge {a}-{b}"
                );
            }
        }
    }
}
