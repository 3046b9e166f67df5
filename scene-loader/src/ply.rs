//! PLY (Stanford polygon file) import.
//!
//! The parser is our own rather than a crate's so that every malformed input, from a
//! bad header to a truncated binary body or a bogus list count, becomes a
//! [`SceneError`] that names the element row at fault instead of a panic or a huge
//! allocation. The whole file is read into memory (scan files are a few MB) and parsed
//! in one pass over the bytes.
//!
//! What is read: the `vertex` element's `x`, `y`, `z`, optional `nx`, `ny`, `nz` and
//! one texture coordinate pair (`u`/`v`, `s`/`t`, `texture_u`/`texture_v` or
//! `texture_s`/`texture_t`), and the `face` element's `vertex_indices` (or
//! `vertex_index`) list, with polygons triangulated as fans. Every other property and
//! element is parsed past (so binary offsets stay right) and dropped.

use std::path::Path;

use dray_core::material::Material;
use dray_core::scene::Scene;
use glam::{Vec2, Vec3};

use crate::error::{Result, SceneError};
use crate::validate::{self, Origin, Primitive};

/// Load a PLY file as a scene with one grey Lambert material.
///
/// PLY carries geometry only, so the scene gets a single `Material::lambert("ply", 0.8)`
/// and the whole file becomes mesh `<file stem>`, primitive 0. Texture coordinates are
/// flipped in v (PLY, like OBJ, puts v = 0 at the bottom of the image; dray's textures
/// put the first row at v = 0, as glTF does).
pub fn load_ply(path: &Path) -> Result<Scene> {
    let bytes = std::fs::read(path).map_err(|source| SceneError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let data = parse(&bytes).map_err(|message| SceneError::Format {
        path: path.to_path_buf(),
        message,
    })?;

    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "ply".to_string());
    let mut scene = Scene {
        name: stem.clone(),
        materials: vec![Material::lambert("ply", Vec3::splat(0.8))],
        ..Scene::default()
    };
    scene.stats.warnings.extend(data.warnings);
    validate::add_primitive(
        &mut scene.mesh,
        &mut scene.stats,
        Origin {
            path,
            mesh: &stem,
            primitive: 0,
        },
        Primitive {
            positions: &data.positions,
            normals: data.normals.as_deref(),
            tangents: None,
            uvs: data.uvs.as_deref(),
            indices: &data.indices,
            material: 0,
        },
    )?;
    if scene.mesh.indices.is_empty() {
        return Err(SceneError::Empty {
            path: path.to_path_buf(),
        });
    }
    Ok(scene)
}

/// Everything the importer keeps from a PLY file.
struct PlyData {
    positions: Vec<Vec3>,
    normals: Option<Vec<Vec3>>,
    uvs: Option<Vec<Vec2>>,
    /// Triangle-list indices, already range-checked against the vertex count.
    indices: Vec<u32>,
    warnings: Vec<String>,
}

type ParseResult<T> = std::result::Result<T, String>;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Format {
    Ascii,
    BinaryLe,
    BinaryBe,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    /// The PLY type names, including the sized aliases some writers (e.g. the zipper
    /// tool behind the Stanford bunny) use.
    fn parse(name: &str) -> Option<Scalar> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    fn is_integer(self) -> bool {
        !matches!(self, Scalar::F32 | Scalar::F64)
    }

    /// The inclusive range of an integer type (floats report the i64 range, unused).
    fn range(self) -> (i64, i64) {
        match self {
            Scalar::I8 => (i8::MIN.into(), i8::MAX.into()),
            Scalar::U8 => (0, u8::MAX.into()),
            Scalar::I16 => (i16::MIN.into(), i16::MAX.into()),
            Scalar::U16 => (0, u16::MAX.into()),
            Scalar::I32 => (i32::MIN.into(), i32::MAX.into()),
            Scalar::U32 => (0, u32::MAX.into()),
            Scalar::F32 | Scalar::F64 => (i64::MIN, i64::MAX),
        }
    }

    fn name(self) -> &'static str {
        match self {
            Scalar::I8 => "char",
            Scalar::U8 => "uchar",
            Scalar::I16 => "short",
            Scalar::U16 => "ushort",
            Scalar::I32 => "int",
            Scalar::U32 => "uint",
            Scalar::F32 => "float",
            Scalar::F64 => "double",
        }
    }
}

#[derive(Clone, Copy, Debug)]
enum Kind {
    Scalar(Scalar),
    /// The header guarantees `count` is an integer type.
    List {
        count: Scalar,
        item: Scalar,
    },
}

#[derive(Debug)]
struct Property {
    name: String,
    kind: Kind,
}

#[derive(Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
}

impl Element {
    /// The fewest bytes one row can occupy, used to cap reservations so a bogus count
    /// in the header cannot make us allocate more than the file could fill.
    fn min_row_bytes(&self, format: Format) -> usize {
        let per_prop = |p: &Property| match (format, p.kind) {
            // A token and a separator.
            (Format::Ascii, _) => 2,
            (_, Kind::Scalar(s)) => s.size(),
            (_, Kind::List { count, .. }) => count.size(),
        };
        self.props.iter().map(per_prop).sum::<usize>().max(1)
    }

    fn capped_reserve(&self, format: Format, remaining: usize) -> usize {
        self.count.min(remaining / self.min_row_bytes(format) + 1)
    }
}

struct Header {
    format: Format,
    elements: Vec<Element>,
    /// Byte offset of the first data byte (just past the `end_header` line).
    data_start: usize,
    /// Lines in the header, so ASCII data errors can give file line numbers.
    lines: usize,
}

fn parse_header(bytes: &[u8]) -> ParseResult<Header> {
    let mut pos = 0usize;
    let mut line_no = 0usize;
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        let rest = bytes.get(pos..).unwrap_or_default();
        if rest.is_empty() {
            return Err(if line_no == 0 {
                "empty file (expected a PLY header)".to_string()
            } else {
                "header has no end_header line".to_string()
            });
        }
        let (raw, next) = match rest.iter().position(|&b| b == b'\n') {
            Some(i) => (rest.get(..i).unwrap_or_default(), pos + i + 1),
            None => (rest, bytes.len()),
        };
        line_no += 1;
        let line = std::str::from_utf8(raw)
            .map_err(|_| format!("header line {line_no} is not text"))?
            .trim();
        let at = |msg: String| format!("header line {line_no}: {msg}");
        if line_no == 1 {
            if line != "ply" {
                return Err("not a PLY file (the first line must be \"ply\")".to_string());
            }
            pos = next;
            continue;
        }
        let mut words = line.split_ascii_whitespace();
        match words.next() {
            None | Some("comment") | Some("obj_info") => {}
            Some("format") => {
                if format.is_some() {
                    return Err(at("second format line".to_string()));
                }
                let f = match words.next() {
                    Some("ascii") => Format::Ascii,
                    Some("binary_little_endian") => Format::BinaryLe,
                    Some("binary_big_endian") => Format::BinaryBe,
                    other => {
                        return Err(at(format!(
                            "unknown format {:?} (expected ascii, binary_little_endian or \
                             binary_big_endian)",
                            other.unwrap_or("")
                        )));
                    }
                };
                if words.next().map(str::parse::<f64>) != Some(Ok(1.0)) {
                    return Err(at("only PLY version 1.0 is supported".to_string()));
                }
                format = Some(f);
            }
            Some("element") => {
                let (Some(name), Some(count)) = (words.next(), words.next()) else {
                    return Err(at("element needs a name and a count".to_string()));
                };
                let count = count.parse::<usize>().map_err(|_| {
                    at(format!(
                        "element {name}: count {count:?} is not a non-negative integer"
                    ))
                })?;
                if elements.iter().any(|e| e.name == name) {
                    return Err(at(format!("element {name} is declared twice")));
                }
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                });
            }
            Some("property") => {
                let Some(element) = elements.last_mut() else {
                    return Err(at("property before any element".to_string()));
                };
                let ty = |name: Option<&str>| -> ParseResult<Scalar> {
                    let name = name.unwrap_or("");
                    Scalar::parse(name).ok_or_else(|| at(format!("unknown type {name:?}")))
                };
                let first = words.next();
                let kind = if first == Some("list") {
                    let count = ty(words.next())?;
                    let item = ty(words.next())?;
                    if !count.is_integer() {
                        return Err(at(format!(
                            "list count type {} is not an integer type",
                            count.name()
                        )));
                    }
                    Kind::List { count, item }
                } else {
                    Kind::Scalar(ty(first)?)
                };
                let Some(name) = words.next() else {
                    return Err(at("property has no name".to_string()));
                };
                element.props.push(Property {
                    name: name.to_string(),
                    kind,
                });
            }
            Some("end_header") => {
                let format = format.ok_or("header has no format line")?;
                return Ok(Header {
                    format,
                    elements,
                    data_start: next,
                    lines: line_no,
                });
            }
            Some(other) => return Err(at(format!("unknown keyword {other:?}"))),
        }
        pos = next;
    }
}

/// A number as read: integers stay exact so indices and counts are never rounded.
#[derive(Clone, Copy, Debug)]
enum Num {
    Int(i64),
    Float(f64),
}

impl Num {
    fn as_f64(self) -> f64 {
        match self {
            Num::Int(i) => i as f64,
            Num::Float(f) => f,
        }
    }
}

/// Reads values from the body in either encoding, always bounds-checked.
struct Cursor<'a> {
    bytes: &'a [u8],
    pos: usize,
    format: Format,
    /// Current line, for ASCII error messages.
    line: usize,
}

impl<'a> Cursor<'a> {
    fn remaining(&self) -> usize {
        self.bytes.len().saturating_sub(self.pos)
    }

    /// Where the cursor is, for error messages.
    fn location(&self) -> String {
        match self.format {
            Format::Ascii => format!("line {}", self.line),
            _ => format!("byte {}", self.pos),
        }
    }

    fn next_token(&mut self) -> Option<&'a [u8]> {
        while let Some(&b) = self.bytes.get(self.pos) {
            if !b.is_ascii_whitespace() {
                break;
            }
            if b == b'\n' {
                self.line += 1;
            }
            self.pos += 1;
        }
        let start = self.pos;
        while let Some(&b) = self.bytes.get(self.pos) {
            if b.is_ascii_whitespace() {
                break;
            }
            self.pos += 1;
        }
        if self.pos == start {
            None
        } else {
            self.bytes.get(start..self.pos)
        }
    }

    fn take(&mut self, n: usize) -> ParseResult<&'a [u8]> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.bytes.len());
        match end.and_then(|e| self.bytes.get(self.pos..e)) {
            Some(s) => {
                self.pos += n;
                Ok(s)
            }
            None => Err(format!(
                "data ends at byte {} but {n} more bytes are needed at byte {} (truncated file?)",
                self.bytes.len(),
                self.pos
            )),
        }
    }

    fn array<const N: usize>(&mut self) -> ParseResult<[u8; N]> {
        let s = self.take(N)?;
        <[u8; N]>::try_from(s).map_err(|_| "internal: short read".to_string())
    }

    fn read(&mut self, ty: Scalar) -> ParseResult<Num> {
        match self.format {
            Format::Ascii => self.read_ascii(ty),
            Format::BinaryLe => self.read_binary(ty, false),
            Format::BinaryBe => self.read_binary(ty, true),
        }
    }

    fn read_binary(&mut self, ty: Scalar, be: bool) -> ParseResult<Num> {
        macro_rules! get {
            ($t:ty, $n:expr) => {{
                let a = self.array::<$n>()?;
                if be {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }
            }};
        }
        Ok(match ty {
            Scalar::I8 => Num::Int(get!(i8, 1).into()),
            Scalar::U8 => Num::Int(get!(u8, 1).into()),
            Scalar::I16 => Num::Int(get!(i16, 2).into()),
            Scalar::U16 => Num::Int(get!(u16, 2).into()),
            Scalar::I32 => Num::Int(get!(i32, 4).into()),
            Scalar::U32 => Num::Int(get!(u32, 4).into()),
            Scalar::F32 => Num::Float(get!(f32, 4).into()),
            Scalar::F64 => Num::Float(get!(f64, 8)),
        })
    }

    fn read_ascii(&mut self, ty: Scalar) -> ParseResult<Num> {
        let tok = self
            .next_token()
            .ok_or_else(|| format!("data ends at line {} (truncated file?)", self.line))?;
        let show = || {
            let s = String::from_utf8_lossy(tok);
            if s.chars().count() > 32 {
                format!("{:?}...", s.chars().take(32).collect::<String>())
            } else {
                format!("{s:?}")
            }
        };
        let text = std::str::from_utf8(tok)
            .map_err(|_| format!("{} at line {} is not a number", show(), self.line))?;
        if ty.is_integer() {
            // Accept integral values written with a decimal point ("3.0"); some writers
            // format every number as a float.
            let v = match text.parse::<i64>() {
                Ok(v) => v,
                Err(_) => match text.parse::<f64>() {
                    Ok(f) if f.is_finite() && f.fract() == 0.0 && f.abs() < 9.0e15 => f as i64,
                    _ => {
                        return Err(format!(
                            "{} at line {} is not an integer",
                            show(),
                            self.line
                        ));
                    }
                },
            };
            let (lo, hi) = ty.range();
            if v < lo || v > hi {
                return Err(format!(
                    "{v} at line {} is out of range for type {}",
                    self.line,
                    ty.name()
                ));
            }
            Ok(Num::Int(v))
        } else {
            text.parse::<f64>()
                .map(Num::Float)
                .map_err(|_| format!("{} at line {} is not a number", show(), self.line))
        }
    }

    fn read_count(&mut self, ty: Scalar) -> ParseResult<usize> {
        match self.read(ty)? {
            Num::Int(n) => usize::try_from(n).map_err(|_| format!("negative list count {n}")),
            Num::Float(_) => Err("list count is not an integer".to_string()),
        }
    }

    /// Read a list's count and make sure the data can hold that many items, so a bogus
    /// count fails here rather than after a long loop or a huge allocation.
    fn read_list_len(&mut self, count: Scalar, item: Scalar) -> ParseResult<usize> {
        let n = self.read_count(count)?;
        let min_bytes = match self.format {
            // Each ASCII item is at least one character and one separator, except that
            // the last one may end the file.
            Format::Ascii => n.saturating_mul(2).saturating_sub(1),
            _ => n.saturating_mul(item.size()),
        };
        if min_bytes > self.remaining() {
            return Err(format!(
                "list count {n} needs at least {min_bytes} bytes but only {} remain",
                self.remaining()
            ));
        }
        Ok(n)
    }

    fn skip(&mut self, kind: Kind) -> ParseResult<()> {
        match (self.format, kind) {
            (Format::Ascii, Kind::Scalar(ty)) => self.read(ty).map(drop),
            (Format::Ascii, Kind::List { count, item }) => {
                let n = self.read_list_len(count, item)?;
                (0..n).try_for_each(|_| self.read(item).map(drop))
            }
            (_, Kind::Scalar(ty)) => self.take(ty.size()).map(drop),
            (_, Kind::List { count, item }) => {
                let n = self.read_list_len(count, item)?;
                self.take(n.saturating_mul(item.size())).map(drop)
            }
        }
    }
}

fn parse(bytes: &[u8]) -> ParseResult<PlyData> {
    let header = parse_header(bytes)?;
    let format = header.format;
    let vertex_count = header
        .elements
        .iter()
        .find(|e| e.name == "vertex")
        .map(|e| e.count)
        .ok_or("header declares no vertex element")?;
    if vertex_count > u32::MAX as usize {
        return Err(format!(
            "{vertex_count} vertices exceed the 32-bit index limit"
        ));
    }
    let mut cur = Cursor {
        bytes,
        pos: header.data_start,
        format,
        line: header.lines + 1,
    };
    let mut data = PlyData {
        positions: Vec::new(),
        normals: None,
        uvs: None,
        indices: Vec::new(),
        warnings: Vec::new(),
    };
    for element in &header.elements {
        match element.name.as_str() {
            "vertex" => read_vertices(&mut cur, element, &mut data)?,
            "face" => read_faces(&mut cur, element, vertex_count, &mut data)?,
            _ => {
                skip_element(&mut cur, element)?;
                if element.count > 0 {
                    data.warnings.push(format!(
                        "PLY element {:?} ({} rows) ignored",
                        element.name, element.count
                    ));
                }
            }
        }
    }
    let trailing = match format {
        Format::Ascii => cur.next_token().is_some(),
        _ => cur.remaining() > 0,
    };
    if trailing {
        data.warnings.push(format!(
            "data after the last PLY element ignored (from {})",
            cur.location()
        ));
    }
    Ok(data)
}

fn skip_element(cur: &mut Cursor<'_>, element: &Element) -> ParseResult<()> {
    if element.props.is_empty() {
        // Rows with no properties occupy no data in either encoding.
        return Ok(());
    }
    let fixed: Option<usize> = element
        .props
        .iter()
        .map(|p| match p.kind {
            Kind::Scalar(s) => Some(s.size()),
            Kind::List { .. } => None,
        })
        .sum();
    if let (Some(row), false) = (fixed, cur.format == Format::Ascii) {
        // Fixed-size binary rows: skip the whole element at once.
        let total = element.count.checked_mul(row);
        return match total {
            Some(t) if t <= cur.remaining() => cur.take(t).map(drop),
            _ => Err(format!(
                "element {}: {} rows of {row} bytes do not fit in the {} bytes left \
                 (truncated file?)",
                element.name,
                element.count,
                cur.remaining()
            )),
        };
    }
    for row in 0..element.count {
        for p in &element.props {
            cur.skip(p.kind)
                .map_err(|e| format!("{} {row}: property {}: {e}", element.name, p.name))?;
        }
    }
    Ok(())
}

/// Slots in the per-vertex scratch buffer.
const X: usize = 0;
const NX: usize = 3;
const U: usize = 6;
const SLOTS: usize = 8;

fn read_vertices(cur: &mut Cursor<'_>, element: &Element, data: &mut PlyData) -> ParseResult<()> {
    let has_scalar = |name: &str| {
        element
            .props
            .iter()
            .any(|p| p.name == name && matches!(p.kind, Kind::Scalar(_)))
    };
    let uv_pair = [
        ("u", "v"),
        ("s", "t"),
        ("texture_u", "texture_v"),
        ("texture_s", "texture_t"),
    ]
    .into_iter()
    .find(|(a, b)| has_scalar(a) && has_scalar(b));
    let slot_of = |p: &Property| -> Option<usize> {
        if !matches!(p.kind, Kind::Scalar(_)) {
            return None;
        }
        let n = p.name.as_str();
        match n {
            "x" => Some(X),
            "y" => Some(X + 1),
            "z" => Some(X + 2),
            "nx" => Some(NX),
            "ny" => Some(NX + 1),
            "nz" => Some(NX + 2),
            _ => match uv_pair {
                Some((a, _)) if n == a => Some(U),
                Some((_, b)) if n == b => Some(U + 1),
                _ => None,
            },
        }
    };
    let slots: Vec<Option<usize>> = element.props.iter().map(slot_of).collect();
    let present = |s: usize| slots.contains(&Some(s));
    for (i, axis) in ["x", "y", "z"].iter().enumerate() {
        if !present(X + i) {
            return Err(format!("vertex element has no scalar property {axis}"));
        }
    }
    let has_normals = (NX..NX + 3).all(present);
    let has_uvs = uv_pair.is_some();

    let cap = element.capped_reserve(cur.format, cur.remaining());
    let mut positions = Vec::with_capacity(cap);
    let mut normals = Vec::with_capacity(if has_normals { cap } else { 0 });
    let mut uvs = Vec::with_capacity(if has_uvs { cap } else { 0 });
    for row in 0..element.count {
        let mut buf = [0.0f64; SLOTS];
        for (p, slot) in element.props.iter().zip(&slots) {
            let at = |e: String| format!("vertex {row}: property {}: {e}", p.name);
            match (p.kind, slot) {
                (Kind::Scalar(ty), Some(s)) => {
                    let v = cur.read(ty).map_err(at)?.as_f64();
                    if let Some(b) = buf.get_mut(*s) {
                        *b = v;
                    }
                }
                (kind, _) => cur.skip(kind).map_err(at)?,
            }
        }
        let [x, y, z, nx, ny, nz, u, v] = buf.map(|f| f as f32);
        positions.push(Vec3::new(x, y, z));
        if has_normals {
            normals.push(Vec3::new(nx, ny, nz));
        }
        if has_uvs {
            uvs.push(Vec2::new(u, 1.0 - v));
        }
    }
    data.positions = positions;
    data.normals = has_normals.then_some(normals);
    data.uvs = has_uvs.then_some(uvs);
    Ok(())
}

fn read_faces(
    cur: &mut Cursor<'_>,
    element: &Element,
    vertex_count: usize,
    data: &mut PlyData,
) -> ParseResult<()> {
    let list = element.props.iter().position(|p| {
        (p.name == "vertex_indices" || p.name == "vertex_index")
            && matches!(p.kind, Kind::List { .. })
    });
    let Some(list) = list else {
        return Err("face element has no vertex_indices list property".to_string());
    };
    if let Some(Property {
        kind: Kind::List { item, .. },
        name,
    }) = element.props.get(list)
        && !item.is_integer()
    {
        return Err(format!(
            "face property {name} has non-integer item type {}",
            item.name()
        ));
    }

    // Most faces are triangles; reserve for that, capped by what the data can hold.
    let cap = element.capped_reserve(cur.format, cur.remaining());
    data.indices.reserve(cap.saturating_mul(3));
    let mut poly: Vec<u32> = Vec::new();
    let mut short_faces = 0u64;
    for row in 0..element.count {
        for (k, p) in element.props.iter().enumerate() {
            let at = |e: String| format!("face {row}: property {}: {e}", p.name);
            match p.kind {
                Kind::List { count, item } if k == list => {
                    let n = cur.read_list_len(count, item).map_err(at)?;
                    poly.clear();
                    for _ in 0..n {
                        let i = match cur.read(item).map_err(at)? {
                            Num::Int(i) => i,
                            Num::Float(_) => return Err(at("index is not an integer".into())),
                        };
                        let idx = usize::try_from(i)
                            .ok()
                            .filter(|&i| i < vertex_count)
                            .and_then(|i| u32::try_from(i).ok())
                            .ok_or_else(|| {
                                format!(
                                    "face {row}: vertex index {i} is out of range \
                                     ({vertex_count} vertices)"
                                )
                            })?;
                        poly.push(idx);
                    }
                    match poly.split_first() {
                        Some((&first, rest)) if rest.len() >= 2 => {
                            for w in rest.windows(2) {
                                if let [b, c] = *w {
                                    data.indices.extend_from_slice(&[first, b, c]);
                                }
                            }
                        }
                        _ => short_faces += 1,
                    }
                }
                kind => cur.skip(kind).map_err(at)?,
            }
        }
    }
    if short_faces > 0 {
        data.warnings.push(format!(
            "{short_faces} PLY faces with fewer than 3 vertices ignored"
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_rejects_garbage() {
        assert!(parse(b"").is_err());
        assert!(parse(b"plx\n").is_err());
        assert!(parse(b"ply\nformat ascii 1.0\n").is_err());
        assert!(parse(b"ply\nformat ascii 2.0\nend_header\n").is_err());
        assert!(parse(b"ply\nformat ascii 1.0\nproperty float x\nend_header\n").is_err());
        assert!(
            parse(
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list float int i\nend_header\n"
            )
            .is_err()
        );
    }

    #[test]
    fn huge_counts_do_not_allocate() {
        let mut f = b"ply\nformat binary_little_endian 1.0\nelement vertex 18446744073709551615\n\
                      property float x\nproperty float y\nproperty float z\nend_header\n"
            .to_vec();
        f.extend_from_slice(&[0u8; 12]);
        let err = parse(&f).err().unwrap_or_default();
        assert!(err.contains("exceed"), "{err}");
    }
}
