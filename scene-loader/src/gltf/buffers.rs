//! The bytes a glTF file refers to: its buffers (the GLB binary chunk, `data:` URIs or
//! files in the scene's folder, read no further than their `byteLength`), the buffer views
//! `EXT_meshopt_compression` stores compressed, and the URI rules (relative paths inside
//! the folder, percent-encoding, base64).

use std::path::Path;

use gltf::json;

use super::format_error;
use crate::error::Result;

/// Read every buffer: the GLB binary chunk, a `data:` URI or a file in the glTF's folder,
/// no further than its `byteLength`.
pub(super) fn load_buffers(
    path: &Path,
    root: &json::Root,
    mut blob: Option<Vec<u8>>,
) -> Result<Vec<Vec<u8>>> {
    let mut out = Vec::with_capacity(root.buffers.len());
    for (i, buffer) in root.buffers.iter().enumerate() {
        let what = match &buffer.uri {
            Some(uri) => format!("buffer {i} ({})", display_uri(uri)),
            None => format!("buffer {i} (GLB binary chunk)"),
        };
        let declared = usize::try_from(buffer.byte_length.0).map_err(|_| {
            format_error(
                path,
                format!("{what}: byteLength {} is too large", buffer.byte_length.0),
            )
        })?;
        let meshopt_ext = buffer
            .extensions
            .as_ref()
            .and_then(|e| e.others.get("EXT_meshopt_compression"));
        if buffer.uri.is_none() && crate::meshopt::is_fallback(meshopt_ext) {
            // Its views are all compressed elsewhere: nothing to read.
            out.push(Vec::new());
            continue;
        }
        let mut data = match &buffer.uri {
            Some(uri) => read_uri(path, uri, Some(buffer.byte_length.0))
                .map_err(|m| format_error(path, format!("{what}: {m}")))?,
            // Only the first buffer may refer to the GLB binary chunk.
            None => match (i, blob.take()) {
                (0, Some(b)) => b,
                _ => {
                    return Err(format_error(
                        path,
                        format!("{what}: buffer has no uri and the file has no GLB binary chunk"),
                    ));
                }
            },
        };
        if data.len() < declared {
            return Err(format_error(
                path,
                format!(
                    "{what}: has {} bytes but its byteLength is {declared} (truncated file?)",
                    data.len()
                ),
            ));
        }
        // Accessors may only read within byteLength; anything past it (GLB padding) goes.
        data.truncate(declared);
        out.push(data);
    }
    Ok(out)
}

/// Decode every buffer view stored with `EXT_meshopt_compression` (see
/// [`crate::meshopt`]); `None` for the views stored plainly.
pub(super) fn decode_meshopt_views(
    path: &Path,
    root: &json::Root,
    buffers: &[Vec<u8>],
) -> Result<Vec<Option<Vec<u8>>>> {
    let mut out = Vec::with_capacity(root.buffer_views.len());
    let buffer_bytes = buffers
        .iter()
        .map(Vec::len)
        .fold(0usize, usize::saturating_add);
    let mut budget = crate::meshopt::DecodeBudget::for_buffers(buffer_bytes);
    for (i, view) in root.buffer_views.iter().enumerate() {
        let Some(ext) = view
            .extensions
            .as_ref()
            .and_then(|e| e.others.get("EXT_meshopt_compression"))
        else {
            out.push(None);
            continue;
        };
        crate::cancel::check()?;
        let what = format!("buffer view {i} (EXT_meshopt_compression)");
        let fail = |m: String| format_error(path, format!("{what}: {m}"));
        let c = crate::meshopt::Compressed::from_json(ext).map_err(fail)?;
        let source = buffers.get(c.buffer).ok_or_else(|| {
            fail(format!(
                "refers to buffer {}, which does not exist",
                c.buffer
            ))
        })?;
        let data = c
            .byte_offset
            .checked_add(c.byte_length)
            .and_then(|end| source.get(c.byte_offset..end))
            .ok_or_else(|| {
                fail(format!(
                    "bytes {}..+{} lie outside buffer {} ({} bytes)",
                    c.byte_offset,
                    c.byte_length,
                    c.buffer,
                    source.len()
                ))
            })?;
        out.push(Some(c.decode(data, &mut budget).map_err(fail)?));
    }
    Ok(out)
}

/// A URI shortened for messages.
pub(super) fn display_uri(uri: &str) -> String {
    crate::reference::display_reference(uri)
}

/// Resolve a buffer or image URI: a `data:` URI, or a relative path that must stay
/// inside the folder of the scene file `scene` and name a regular file, read no further
/// than `limit` bytes when given (a buffer's byteLength). Other schemes (`file:`,
/// `http:`, ...) and absolute paths are refused. Messages never quote file contents.
pub(super) fn read_uri(
    scene: &Path,
    uri: &str,
    limit: Option<u64>,
) -> std::result::Result<Vec<u8>, String> {
    if let Some(rest) = uri.strip_prefix("data:") {
        let (header, payload) = rest
            .split_once(',')
            .ok_or_else(|| "data URI has no ',' before its payload".to_string())?;
        return if header.ends_with(";base64") {
            decode_base64(payload).map_err(|m| format!("data URI: {m}"))
        } else {
            percent_decode(payload).map_err(|m| format!("data URI: {m}"))
        };
    }
    match uri_scheme(uri) {
        Some(scheme) if scheme.eq_ignore_ascii_case("file") => {
            return Err(
                "file: URIs are not allowed (a scene may only refer to files in its own \
                 folder, by relative path)"
                    .to_string(),
            );
        }
        Some(scheme) => {
            return Err(format!(
                "URI scheme {} is not supported (only relative paths and data: URIs)",
                display_uri(scheme)
            ));
        }
        None => {}
    }
    let relative = utf8(percent_decode(uri)?)?;
    let opened =
        crate::reference::open_in_scene_folder(scene, &relative).map_err(|e| e.message())?;
    let len = opened.len;
    if let Some(declared) = limit
        && len < declared
    {
        return Err(format!(
            "file has {len} bytes but the buffer's byteLength is {declared} (truncated file?)"
        ));
    }
    opened
        .read_at_most(limit.unwrap_or(len))
        .map_err(|e| format!("cannot read: {}", e.kind()))
}

pub(super) fn utf8(bytes: Vec<u8>) -> std::result::Result<String, String> {
    String::from_utf8(bytes).map_err(|_| "URI is not valid UTF-8 after percent-decoding".into())
}

/// The scheme of an absolute URI (RFC 3986: a letter, then letters, digits, `+-.`),
/// or `None` for a relative reference. One-letter schemes are taken as Windows drives.
pub(super) fn uri_scheme(uri: &str) -> Option<&str> {
    let (scheme, _) = uri.split_once(':')?;
    let mut chars = scheme.chars();
    let first = chars.next()?;
    let ok = first.is_ascii_alphabetic()
        && chars.all(|c| c.is_ascii_alphanumeric() || matches!(c, '+' | '-' | '.'));
    (ok && scheme.len() > 1).then_some(scheme)
}

pub(super) fn percent_decode(s: &str) -> std::result::Result<Vec<u8>, String> {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while let Some(&b) = bytes.get(i) {
        if b == b'%' {
            let hex = |at: usize| bytes.get(at).and_then(|&c| (c as char).to_digit(16));
            match (hex(i + 1), hex(i + 2)) {
                (Some(h), Some(l)) => out.push((h * 16 + l) as u8),
                _ => return Err(format!("malformed percent-encoding at byte {i}")),
            }
            i += 3;
        } else {
            out.push(b);
            i += 1;
        }
    }
    Ok(out)
}

/// Standard (and URL-safe) base64, padding optional, ASCII whitespace ignored. Written
/// here rather than adding a dependency for one small function.
pub(super) fn decode_base64(s: &str) -> std::result::Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(s.len() / 4 * 3 + 3);
    let mut acc: u32 = 0;
    let mut bits = 0u32;
    let mut digits = 0usize;
    for (i, c) in s.bytes().enumerate() {
        let v = match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' | b'-' => 62,
            b'/' | b'_' => 63,
            b'=' => break,
            c if c.is_ascii_whitespace() => continue,
            _ => return Err(format!("invalid base64 character {:?} at {i}", c as char)),
        };
        acc = (acc << 6) | u32::from(v);
        bits += 6;
        digits += 1;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    if digits % 4 == 1 {
        return Err("base64 payload is truncated".into());
    }
    Ok(out)
}
