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
    pub fn decode(&self, data: &[u8]) -> Result<Vec<u8>, String> {
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
        let mut out = vec![0u8; bytes];
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

/// True when a buffer is only a placeholder for data that is present compressed
/// (`EXT_meshopt_compression.fallback`): it has no bytes to read.
pub fn is_fallback(buffer_extensions: Option<&Value>) -> bool {
    buffer_extensions
        .and_then(|e| e.get("fallback"))
        .and_then(Value::as_bool)
        .unwrap_or(false)
}
