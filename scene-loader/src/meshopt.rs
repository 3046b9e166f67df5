//! `EXT_meshopt_compression`: buffer views stored compressed by meshoptimizer's codecs,
//! decoded at load into plain bytes that the accessors then read as usual.
//!
//! The decoding is meshoptimizer's own (the `meshopt` crate builds its C++ source),
//! which is written to be safe on untrusted input: a malformed stream is an error
//! code, never a read or write out of bounds, provided the sizes passed to it are
//! those it asserts on. Those are checked here first, so a bad file is an error that
//! names the buffer view, never an abort.

use serde_json::Value;

/// Upper bound on a decoded buffer view, so a tiny file cannot ask for a huge
/// allocation (the output size is `count * byteStride`, both from the file).
const MAX_DECODED_BYTES: usize = 1 << 31;

/// The most meshoptimizer's codecs expand their input: version 1 of the attribute codec
/// spends one control byte on four byte channels of a block of up to 256 vertices when
/// they are all zero (1024:1; version 0's smallest group is 2 bits for 16 bytes, 64:1);
/// the index codecs spend at least a byte a triangle (12:1) or an index (4:1). A view
/// that claims more than this times its compressed bytes (plus a block's slack) cannot
/// be real, and a file's views together decode to at most this times the bytes of its
/// buffers: twelve views naming one stream (a decompression bomb) share one allowance,
/// not twelve. The bound that matters for memory is admission's, which prices the
/// declared total ([`declared_decoded_bytes`]) before anything is loaded; this one keeps
/// a file from asking for what its bytes cannot hold.
pub const MAX_EXPANSION: usize = 1024;

/// Decoded bytes a view may claim beyond [`MAX_EXPANSION`] times its input: one block
/// of the largest vertex (256 vertices of 256 bytes).
const EXPANSION_SLACK: usize = 256 * 256;

/// Bytes a file's compressed views may still decode to ([`MAX_EXPANSION`] times its
/// buffers' bytes), drawn down view by view.
#[derive(Clone, Copy, Debug)]
pub struct DecodeBudget {
    left: usize,
}

impl DecodeBudget {
    /// The allowance of a file whose buffers hold `buffer_bytes` bytes in all.
    pub fn for_buffers(buffer_bytes: usize) -> DecodeBudget {
        DecodeBudget {
            left: buffer_bytes.saturating_mul(MAX_EXPANSION),
        }
    }

    /// Take `bytes` from the allowance, or say why not.
    fn take(&mut self, bytes: usize) -> Result<(), String> {
        if bytes > self.left {
            return Err(format!(
                "decodes to {bytes} bytes, beyond what is left of the file's allowance \
                 ({} bytes: compressed views decode to at most {MAX_EXPANSION} times the \
                 bytes of the file's buffers, all views together)",
                self.left
            ));
        }
        self.left -= bytes;
        Ok(())
    }
}

/// One compressed buffer view as the extension describes it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Compressed {
    pub buffer: usize,
    pub byte_offset: usize,
    pub byte_length: usize,
    pub byte_stride: usize,
    pub count: usize,
    pub mode: Mode,
    pub filter: Filter,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    Attributes,
    Triangles,
    Indices,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Filter {
    None,
    Octahedral,
    Quaternion,
    Exponential,
}

impl Compressed {
    /// The extension object of a buffer view, or a message saying what is wrong with it.
    pub fn from_json(ext: &Value) -> Result<Compressed, String> {
        let size = |key: &str, default: Option<usize>| -> Result<usize, String> {
            match ext.get(key) {
                Some(v) => v
                    .as_u64()
                    .and_then(|v| usize::try_from(v).ok())
                    .ok_or_else(|| format!("{key} is not a non-negative integer")),
                None => default.ok_or_else(|| format!("{key} is missing")),
            }
        };
        let mode = match ext.get("mode").and_then(Value::as_str) {
            Some("ATTRIBUTES") => Mode::Attributes,
            Some("TRIANGLES") => Mode::Triangles,
            Some("INDICES") => Mode::Indices,
            _ => return Err("mode must be ATTRIBUTES, TRIANGLES or INDICES".into()),
        };
        let filter = match ext.get("filter").map(Value::as_str) {
            None | Some(Some("NONE")) => Filter::None,
            Some(Some("OCTAHEDRAL")) => Filter::Octahedral,
            Some(Some("QUATERNION")) => Filter::Quaternion,
            Some(Some("EXPONENTIAL")) => Filter::Exponential,
            _ => return Err("filter must be NONE, OCTAHEDRAL, QUATERNION or EXPONENTIAL".into()),
        };
        Ok(Compressed {
            buffer: size("buffer", None)?,
            byte_offset: size("byteOffset", Some(0))?,
            byte_length: size("byteLength", None)?,
            byte_stride: size("byteStride", None)?,
            count: size("count", None)?,
            mode,
            filter,
        })
    }

    /// Decode `data` (the `byteLength` bytes at `byteOffset` of the compressed buffer)
    /// into `count * byteStride` bytes.
    ///
    /// The output is taken from `budget` before it is allocated, and allocated fallibly:
    /// a file that asks for more than the process can have is an error, never an abort.
    pub fn decode(&self, data: &[u8], budget: &mut DecodeBudget) -> Result<Vec<u8>, String> {
        let (stride, count) = (self.byte_stride, self.count);
        let stride_ok = match self.mode {
            Mode::Attributes => stride > 0 && stride <= 256 && stride.is_multiple_of(4),
            Mode::Triangles | Mode::Indices => stride == 2 || stride == 4,
        };
        if !stride_ok {
            return Err(format!(
                "byteStride {stride} is not allowed in mode {:?} (attributes: a multiple of 4 \
                 up to 256; indices: 2 or 4)",
                self.mode
            ));
        }
        let filter_ok = match self.filter {
            Filter::None => true,
            Filter::Octahedral => stride == 4 || stride == 8,
            Filter::Quaternion => stride == 8,
            Filter::Exponential => stride.is_multiple_of(4),
        };
        if !filter_ok || (self.filter != Filter::None && self.mode != Mode::Attributes) {
            return Err(format!(
                "filter {:?} does not apply to mode {:?} with byteStride {stride}",
                self.filter, self.mode
            ));
        }
        if self.mode == Mode::Triangles && !count.is_multiple_of(3) {
            return Err(format!(
                "mode TRIANGLES needs a count divisible by 3, not {count}"
            ));
        }
        let bytes = count
            .checked_mul(stride)
            .filter(|&b| b <= MAX_DECODED_BYTES)
            .ok_or_else(|| format!("count {count} x byteStride {stride} is too large"))?;
        let possible = data
            .len()
            .saturating_mul(MAX_EXPANSION)
            .saturating_add(EXPANSION_SLACK);
        if bytes > possible {
            return Err(format!(
                "count {count} x byteStride {stride} = {bytes} bytes cannot come from {} \
                 compressed bytes (meshoptimizer expands at most {MAX_EXPANSION}-fold)",
                data.len()
            ));
        }
        budget.take(bytes)?;
        let mut out = Vec::new();
        out.try_reserve_exact(bytes)
            .map_err(|_| format!("cannot allocate {bytes} bytes to decode it"))?;
        out.resize(bytes, 0u8);
        // SAFETY: `out` holds exactly `count * stride` bytes, the output size each
        // decoder writes for `count` elements of `stride` bytes; `data` is a valid slice
        // passed with its length, which the decoders never read past; the stride values
        // are those the decoders accept (checked above), so their assertions hold.
        let code = unsafe {
            use meshopt::ffi;
            let dst = out.as_mut_ptr().cast::<std::ffi::c_void>();
            match self.mode {
                Mode::Attributes => {
                    ffi::meshopt_decodeVertexBuffer(dst, count, stride, data.as_ptr(), data.len())
                }
                Mode::Triangles => {
                    ffi::meshopt_decodeIndexBuffer(dst, count, stride, data.as_ptr(), data.len())
                }
                Mode::Indices => {
                    ffi::meshopt_decodeIndexSequence(dst, count, stride, data.as_ptr(), data.len())
                }
            }
        };
        if code != 0 {
            return Err(format!(
                "the compressed data is malformed (meshoptimizer decoder error {code})"
            ));
        }
        // SAFETY: as above: `out` holds `count` elements of `stride` bytes, a stride each
        // filter accepts.
        unsafe {
            use meshopt::ffi;
            let dst = out.as_mut_ptr().cast::<std::ffi::c_void>();
            match self.filter {
                Filter::None => {}
                Filter::Octahedral => ffi::meshopt_decodeFilterOct(dst, count, stride),
                Filter::Quaternion => ffi::meshopt_decodeFilterQuat(dst, count, stride),
                Filter::Exponential => ffi::meshopt_decodeFilterExp(dst, count, stride),
            }
        }
        Ok(out)
    }
}

/// The bytes the compressed views of a glTF document (its JSON) declare they decode to,
/// all views together: what loading the file allocates beyond its own size, for
/// admission to count before the file is loaded. Views that are malformed count nothing
/// (the load refuses them).
pub fn declared_decoded_bytes(root: &Value) -> u64 {
    let Some(views) = root.get("bufferViews").and_then(Value::as_array) else {
        return 0;
    };
    views
        .iter()
        .filter_map(|v| v.get("extensions")?.get("EXT_meshopt_compression"))
        .filter_map(|ext| Compressed::from_json(ext).ok())
        .map(|c| (c.count as u64).saturating_mul(c.byte_stride as u64))
        .fold(0u64, u64::saturating_add)
}

/// True when a buffer is only a placeholder for data that is present compressed
/// (`EXT_meshopt_compression.fallback`): it has no bytes to read.
pub fn is_fallback(buffer_extensions: Option<&Value>) -> bool {
    buffer_extensions
        .and_then(|e| e.get("fallback"))
        .and_then(Value::as_bool)
        .unwrap_or(false)
}
