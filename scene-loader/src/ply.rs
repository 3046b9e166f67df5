//! PLY (Stanford polygon file) import.
//!
//! The parser is our own rather than a crate's so that every malformed input, from a
//! bad header to a truncated binary body or a bogus list count, becomes a
//! [`SceneError`] that names the element row at fault instead of a panic or a huge
//! allocation. The file is read through a small window ([`CHUNK`]-sized refills) rather
//! than whole, so that `dray partition` can stream a scan larger than memory (see
//! [`crate::ply_stream`]) through the very same code the in-memory loader uses: both
//! drive [`read_body`] and differ only in what their [`Body`] does with the vertices and
//! triangles it hands over.
//!
//! What is read: the `vertex` element's `x`, `y`, `z`, optional `nx`, `ny`, `nz` and
//! one texture coordinate pair (`u`/`v`, `s`/`t`, `texture_u`/`texture_v` or
//! `texture_s`/`texture_t`), and the `face` element's `vertex_indices` (or
//! `vertex_index`) list, with polygons triangulated as fans. Every other property and
//! element is parsed past (so binary offsets stay right) and dropped.

use std::io::Read;
use std::ops::Range;
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
    let mut body = Collect::default();
    let warnings = read_file(path, &mut body)?;
    let stem = mesh_name(path);
    let mut scene = tables(path, warnings);
    let vertices = body.vertices.unwrap_or_default();
    validate::add_primitive(
        &mut scene.mesh,
        &mut scene.stats,
        Origin {
            path,
            mesh: &stem,
            primitive: 0,
        },
        Primitive {
            positions: &vertices.positions,
            normals: vertices.normals.as_deref(),
            tangents: None,
            uvs: vertices.uvs.as_deref(),
            uvs2: None,
            uv_sets: [0, 1],
            colors: None,
            indices: &body.indices,
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

/// The mesh (and scene) name a PLY file gets: its file stem.
pub(crate) fn mesh_name(path: &Path) -> String {
    path.file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "ply".to_string())
}

/// Everything of a PLY scene but its mesh: name, the one material and the parse
/// warnings. Shared with the stream so both report the same tables.
pub(crate) fn tables(path: &Path, warnings: Vec<String>) -> Scene {
    let mut scene = Scene {
        name: mesh_name(path),
        materials: vec![Material::lambert("ply", Vec3::splat(0.8))],
        ..Scene::default()
    };
    scene.stats.warnings = warnings;
    scene
}

/// Open `path` and run one pass of [`read_body`] over it, returning the parse warnings.
pub(crate) fn read_file(path: &Path, body: &mut dyn Body) -> Result<Vec<String>> {
    let opened = crate::reference::open_scene_file(path)?;
    let len = usize::try_from(opened.len).unwrap_or(usize::MAX);
    // No further than the length the file had when opened.
    let mut file = opened.file.take(opened.len);
    read_body(&mut file, len, body).map_err(|stop| match stop {
        Stop::Format(message) => SceneError::Format {
            path: path.to_path_buf(),
            message,
        },
        Stop::Scene(e) => e,
    })
}

/// Whether `path`'s header declares its face element before its vertex element (legal
/// PLY, but a stream cannot resolve indices to vertices it has not read yet).
pub(crate) fn faces_before_vertices(path: &Path) -> Result<bool> {
    let opened = crate::reference::open_scene_file(path)?;
    let len = opened.len;
    let mut file = opened.file.take(len);
    let mut cur = Cursor::new(&mut file, usize::try_from(len).unwrap_or(usize::MAX));
    let header = parse_header(&mut cur).map_err(|message| SceneError::Format {
        path: path.to_path_buf(),
        message,
    })?;
    let at = |name: &str| header.elements.iter().position(|e| e.name == name);
    Ok(matches!((at("face"), at("vertex")), (Some(f), Some(v)) if f < v))
}

/// The vertex attributes a PLY file has, as read (normals not yet normalized, v already
/// flipped).
#[derive(Default)]
pub(crate) struct Vertices {
    pub positions: Vec<Vec3>,
    pub normals: Option<Vec<Vec3>>,
    pub uvs: Option<Vec<Vec2>>,
}

/// Why a pass stopped: a malformed file (the message, to be given the path), or an error
/// the [`Body`] raised.
pub(crate) enum Stop {
    Format(String),
    Scene(SceneError),
}

impl From<String> for Stop {
    fn from(message: String) -> Stop {
        Stop::Format(message)
    }
}

impl From<SceneError> for Stop {
    fn from(e: SceneError) -> Stop {
        Stop::Scene(e)
    }
}

/// What a pass does with the data [`read_body`] parses.
pub(crate) trait Body {
    /// The vertex element, once, when it has been read.
    fn vertices(&mut self, vertices: Vertices) -> std::result::Result<(), Stop>;
    /// A hint before the face element: it has `rows` rows (capped by what the data can
    /// hold, so a bogus count cannot make a reservation huge).
    fn reserve_faces(&mut self, _rows: usize) {}
    /// One triangle of a face's fan, in file order, indices already range-checked.
    fn triangle(&mut self, tri: [u32; 3]) -> std::result::Result<(), Stop>;
}

/// The in-memory loader's body: keeps the vertices and every index.
#[derive(Default)]
struct Collect {
    vertices: Option<Vertices>,
    /// Triangle-list indices, already range-checked against the vertex count.
    indices: Vec<u32>,
}

impl Body for Collect {
    fn vertices(&mut self, vertices: Vertices) -> std::result::Result<(), Stop> {
        self.vertices = Some(vertices);
        Ok(())
    }
    fn reserve_faces(&mut self, rows: usize) {
        // Most faces are triangles.
        self.indices.reserve(rows.saturating_mul(3));
    }
    fn triangle(&mut self, tri: [u32; 3]) -> std::result::Result<(), Stop> {
        self.indices.extend_from_slice(&tri);
        Ok(())
    }
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
}

/// Header lines longer than this are refused rather than buffered: a real header line is
/// a few dozen bytes, and a binary file misnamed `.ply` may have no newline for a long way.
const MAX_HEADER_LINE: usize = 64 * 1024;

/// Read the header, leaving `cur` at the first data byte and on the first data line.
fn parse_header(cur: &mut Cursor<'_>) -> ParseResult<Header> {
    let mut line_no = 0usize;
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        let Some(raw) = cur.read_line(MAX_HEADER_LINE)? else {
            return Err(if line_no == 0 {
                "empty file (expected a PLY header)".to_string()
            } else {
                "header has no end_header line".to_string()
            });
        };
        line_no += 1;
        let Some(raw) = raw else {
            return Err(if line_no == 1 {
                "not a PLY file (the first line must be \"ply\")".to_string()
            } else {
                format!("header line {line_no} is longer than {MAX_HEADER_LINE} bytes")
            });
        };
        let line = std::str::from_utf8(&raw)
            .map_err(|_| format!("header line {line_no} is not text"))?
            .trim();
        let at = |msg: String| format!("header line {line_no}: {msg}");
        if line_no == 1 {
            if line != "ply" {
                return Err("not a PLY file (the first line must be \"ply\")".to_string());
            }
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
                cur.format = format;
                cur.line = line_no + 1;
                return Ok(Header { format, elements });
            }
            Some(other) => return Err(at(format!("unknown keyword {other:?}"))),
        }
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

/// How much the cursor reads at a time: big enough that refills cost nothing next to
/// parsing, small enough that a pass over a multi-GB file holds next to none of it.
const CHUNK: usize = 1 << 20;

/// Reads values from the input in either encoding, always bounds-checked, through a
/// window of the input that is refilled as it is consumed.
struct Cursor<'r> {
    reader: &'r mut dyn Read,
    /// The window: input bytes from offset `base` on.
    buf: Vec<u8>,
    /// Index in `buf` of the next unread byte.
    at: usize,
    /// Input offset of `buf[0]`.
    base: usize,
    /// Length of the whole input (the file's size), for "remaining" checks that keep a
    /// bogus count from causing a long loop or a huge allocation.
    len: usize,
    /// The reader has nothing more.
    eof: bool,
    format: Format,
    /// Current line, for ASCII error messages.
    line: usize,
}

impl<'r> Cursor<'r> {
    fn new(reader: &'r mut dyn Read, len: usize) -> Self {
        Cursor {
            reader,
            buf: Vec::new(),
            at: 0,
            base: 0,
            len,
            eof: false,
            format: Format::Ascii,
            line: 1,
        }
    }

    /// Input offset of the next unread byte.
    fn pos(&self) -> usize {
        self.base + self.at
    }

    fn remaining(&self) -> usize {
        self.len.saturating_sub(self.pos())
    }

    /// Bytes in the window not yet consumed.
    fn available(&self) -> usize {
        self.buf.len().saturating_sub(self.at)
    }

    /// Make the window hold at least `need` unread bytes, or everything that is left.
    /// Consumed bytes are dropped first, so the window stays about [`CHUNK`] in size.
    fn fill(&mut self, need: usize) -> ParseResult<()> {
        while self.available() < need && !self.eof {
            if self.at > 0 {
                self.buf.drain(..self.at);
                self.base += self.at;
                self.at = 0;
            }
            let old = self.buf.len();
            self.buf.resize(old + (need - old).max(CHUNK), 0);
            let got = loop {
                match self
                    .reader
                    .read(self.buf.get_mut(old..).unwrap_or_default())
                {
                    Ok(n) => break Ok(n),
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                    Err(e) => break Err(e),
                }
            };
            let n = match got {
                Ok(n) => n,
                Err(e) => {
                    self.buf.truncate(old);
                    return Err(format!("cannot read at byte {}: {e}", self.base + old));
                }
            };
            self.buf.truncate(old + n);
            self.eof = n == 0;
        }
        Ok(())
    }

    /// Where the cursor is, for error messages.
    fn location(&self) -> String {
        match self.format {
            Format::Ascii => format!("line {}", self.line),
            _ => format!("byte {}", self.pos()),
        }
    }

    /// The next line without its `\n`: `None` at the end of the input, `Some(None)` when
    /// it is longer than `limit`.
    fn read_line(&mut self, limit: usize) -> ParseResult<Option<Option<Vec<u8>>>> {
        let mut scanned = 0;
        loop {
            let window = self.buf.get(self.at..).unwrap_or_default();
            if let Some(i) = window.iter().skip(scanned).position(|&b| b == b'\n') {
                let end = scanned + i;
                if end > limit {
                    return Ok(Some(None));
                }
                let line = window.get(..end).unwrap_or_default().to_vec();
                self.at += end + 1;
                return Ok(Some(Some(line)));
            }
            scanned = window.len();
            if scanned > limit {
                return Ok(Some(None));
            }
            self.fill(scanned + 1)?;
            if self.available() == scanned {
                // The last line has no newline.
                if scanned == 0 {
                    return Ok(None);
                }
                let line = self.buf.get(self.at..).unwrap_or_default().to_vec();
                self.at = self.buf.len();
                return Ok(Some(Some(line)));
            }
        }
    }

    /// The next whitespace-separated token, as a range of `buf` valid until the next read.
    fn next_token(&mut self) -> ParseResult<Option<Range<usize>>> {
        loop {
            self.fill(1)?;
            match self.buf.get(self.at) {
                Some(&b) if b.is_ascii_whitespace() => {
                    if b == b'\n' {
                        self.line += 1;
                    }
                    self.at += 1;
                }
                Some(_) => break,
                None => return Ok(None),
            }
        }
        let mut len = 0;
        loop {
            match self.buf.get(self.at + len) {
                Some(b) if !b.is_ascii_whitespace() => len += 1,
                Some(_) => break,
                None => {
                    // Refilling keeps the unread bytes (the token so far) in the window.
                    self.fill(len + 1)?;
                    if self.available() <= len {
                        break;
                    }
                }
            }
        }
        let token = self.at..self.at + len;
        self.at += len;
        Ok(Some(token))
    }

    fn truncated(&self, n: usize) -> String {
        format!(
            "data ends at byte {} but {n} more bytes are needed at byte {} (truncated file?)",
            if self.eof {
                self.base + self.buf.len()
            } else {
                self.len
            },
            self.pos()
        )
    }

    fn take(&mut self, n: usize) -> ParseResult<&[u8]> {
        self.fill(n)?;
        if self.available() < n {
            return Err(self.truncated(n));
        }
        let start = self.at;
        self.at += n;
        Ok(self.buf.get(start..start + n).unwrap_or_default())
    }

    /// Consume `n` bytes without keeping them (a whole skipped element can be large).
    fn skip_bytes(&mut self, n: usize) -> ParseResult<()> {
        let mut left = n;
        loop {
            let k = self.available().min(left);
            self.at += k;
            left -= k;
            if left == 0 {
                return Ok(());
            }
            self.fill(left.min(CHUNK))?;
            if self.available() == 0 {
                return Err(self.truncated(left));
            }
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
        let Some(range) = self.next_token()? else {
            return Err(format!("data ends at line {} (truncated file?)", self.line));
        };
        let tok = self.buf.get(range).unwrap_or_default();
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
            (_, Kind::Scalar(ty)) => self.skip_bytes(ty.size()),
            (_, Kind::List { count, item }) => {
                let n = self.read_list_len(count, item)?;
                self.skip_bytes(n.saturating_mul(item.size()))
            }
        }
    }
}

/// One pass over a PLY input of `len` bytes: the header, then every element in file
/// order, with the vertex element and each face's triangles handed to `body`. Returns the
/// warnings (ignored elements, short faces, trailing data).
pub(crate) fn read_body(
    reader: &mut dyn Read,
    len: usize,
    body: &mut dyn Body,
) -> std::result::Result<Vec<String>, Stop> {
    let mut cur = Cursor::new(reader, len);
    let header = parse_header(&mut cur)?;
    let vertex_count = header
        .elements
        .iter()
        .find(|e| e.name == "vertex")
        .map(|e| e.count)
        .ok_or("header declares no vertex element".to_string())?;
    if vertex_count > u32::MAX as usize {
        return Err(format!("{vertex_count} vertices exceed the 32-bit index limit").into());
    }
    let mut warnings = Vec::new();
    for element in &header.elements {
        match element.name.as_str() {
            "vertex" => body.vertices(read_vertices(&mut cur, element)?)?,
            "face" => read_faces(&mut cur, element, vertex_count, body, &mut warnings)?,
            _ => {
                skip_element(&mut cur, element)?;
                if element.count > 0 {
                    warnings.push(format!(
                        "PLY element {:?} ({} rows) ignored",
                        element.name, element.count
                    ));
                }
            }
        }
    }
    let trailing = match header.format {
        Format::Ascii => cur.next_token()?.is_some(),
        _ => cur.remaining() > 0,
    };
    if trailing {
        warnings.push(format!(
            "data after the last PLY element ignored (from {})",
            cur.location()
        ));
    }
    Ok(warnings)
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
            Some(t) if t <= cur.remaining() => cur.skip_bytes(t),
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

fn read_vertices(cur: &mut Cursor<'_>, element: &Element) -> std::result::Result<Vertices, Stop> {
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
            return Err(format!("vertex element has no scalar property {axis}").into());
        }
    }
    let has_normals = (NX..NX + 3).all(present);
    let has_uvs = uv_pair.is_some();

    let cap = element.capped_reserve(cur.format, cur.remaining());
    let mut positions = Vec::with_capacity(cap);
    let mut normals = Vec::with_capacity(if has_normals { cap } else { 0 });
    let mut uvs = Vec::with_capacity(if has_uvs { cap } else { 0 });
    for row in 0..element.count {
        crate::cancel::check_at(row)?;
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
    Ok(Vertices {
        positions,
        normals: has_normals.then_some(normals),
        uvs: has_uvs.then_some(uvs),
    })
}

fn read_faces(
    cur: &mut Cursor<'_>,
    element: &Element,
    vertex_count: usize,
    body: &mut dyn Body,
    warnings: &mut Vec<String>,
) -> std::result::Result<(), Stop> {
    let list = element.props.iter().position(|p| {
        (p.name == "vertex_indices" || p.name == "vertex_index")
            && matches!(p.kind, Kind::List { .. })
    });
    let Some(list) = list else {
        return Err("face element has no vertex_indices list property"
            .to_string()
            .into());
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
        )
        .into());
    }

    body.reserve_faces(element.capped_reserve(cur.format, cur.remaining()));
    let mut poly: Vec<u32> = Vec::new();
    let mut short_faces = 0u64;
    for row in 0..element.count {
        crate::cancel::check_at(row)?;
        for (k, p) in element.props.iter().enumerate() {
            let at = |e: String| format!("face {row}: property {}: {e}", p.name);
            match p.kind {
                Kind::List { count, item } if k == list => {
                    let n = cur.read_list_len(count, item).map_err(at)?;
                    poly.clear();
                    for _ in 0..n {
                        let i = match cur.read(item).map_err(at)? {
                            Num::Int(i) => i,
                            Num::Float(_) => {
                                return Err(at("index is not an integer".into()).into());
                            }
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
                                    body.triangle([first, b, c])?;
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
        warnings.push(format!(
            "{short_faces} PLY faces with fewer than 3 vertices ignored"
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Parse `bytes` as the in-memory loader does, errors as their messages.
    fn parse(bytes: &[u8]) -> ParseResult<Vec<String>> {
        let mut input = bytes;
        read_body(&mut input, bytes.len(), &mut Collect::default()).map_err(|e| match e {
            Stop::Format(m) => m,
            Stop::Scene(e) => e.to_string(),
        })
    }

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

    /// Hands out at most one byte per read, so every window refill path (mid-token,
    /// mid-value, mid-line) is taken.
    struct Trickle<'a>(&'a [u8]);

    impl Read for Trickle<'_> {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            match (self.0.split_first(), buf.first_mut()) {
                (Some((&b, rest)), Some(slot)) => {
                    *slot = b;
                    self.0 = rest;
                    Ok(1)
                }
                _ => Ok(0),
            }
        }
    }

    fn collect(bytes: &[u8], trickle: bool) -> (Vec<Vec3>, Vec<u32>, Vec<String>) {
        let mut body = Collect::default();
        let warnings = if trickle {
            read_body(&mut Trickle(bytes), bytes.len(), &mut body)
        } else {
            let mut input = bytes;
            read_body(&mut input, bytes.len(), &mut body)
        };
        let warnings = match warnings {
            Ok(w) => w,
            Err(Stop::Format(m)) => vec![format!("error: {m}")],
            Err(Stop::Scene(e)) => vec![format!("error: {e}")],
        };
        let positions = body.vertices.map(|v| v.positions).unwrap_or_default();
        (positions, body.indices, warnings)
    }

    #[test]
    fn a_trickling_reader_parses_the_same() {
        let ascii = b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\n\
                      property float y\nproperty float z\nelement face 2\n\
                      property list uchar int vertex_indices\nend_header\n\
                      0 0 0\n1.5 0 0\n1 1 0\n0 1 0.25\n4 0 1 2 3\n3 0 2 3\n9\n";
        let mut binary = b"ply\nformat binary_big_endian 1.0\nelement vertex 3\n\
                           property double x\nproperty double y\nproperty double z\n\
                           element face 1\nproperty list uchar uint vertex_indices\n\
                           end_header\n"
            .to_vec();
        for c in [0.0f64, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0] {
            binary.extend_from_slice(&c.to_be_bytes());
        }
        binary.push(3);
        for i in [0u32, 1, 2] {
            binary.extend_from_slice(&i.to_be_bytes());
        }
        for bytes in [&ascii[..], &binary[..], &binary[..binary.len() - 2]] {
            let whole = collect(bytes, false);
            assert_eq!(collect(bytes, true), whole);
            assert!(!whole.0.is_empty(), "{whole:?}");
        }
        assert_eq!(collect(ascii, false).1, vec![0, 1, 2, 0, 2, 3, 0, 2, 3]);
    }
}
