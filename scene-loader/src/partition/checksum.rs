//! Checksums for package files: XXH3-64 (the `xxhash-rust` crate).
//!
//! The checksum guards against truncation, bit rot and half-copied packages, not against
//! an adversary, so a fast non-cryptographic hash is the right tool: XXH3 hashes at memory
//! bandwidth, so verifying a domain costs about as much as reading it. Checksums are
//! written as 16 lowercase hex digits, which JSON carries without precision loss (a u64 as
//! a JSON number would not survive JavaScript-based tools).

use std::io::{self, Read, Write};

use xxhash_rust::xxh3::{Xxh3Default, xxh3_64};

/// The one-shot checksum of `bytes`.
pub fn checksum(bytes: &[u8]) -> u64 {
    xxh3_64(bytes)
}

/// `value` as 16 lowercase hex digits.
pub fn to_hex(value: u64) -> String {
    format!("{value:016x}")
}

/// Parse what [`to_hex`] wrote; anything else is `None`.
pub fn from_hex(text: &str) -> Option<u64> {
    if text.len() != 16 || !text.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    u64::from_str_radix(text, 16).ok()
}

/// A writer that hashes and counts every byte on its way to `inner`, so a file's checksum
/// and size come out of the single pass that writes it.
pub struct HashingWriter<W> {
    inner: W,
    hasher: Box<Xxh3Default>,
    written: u64,
}

impl<W: Write> HashingWriter<W> {
    pub fn new(inner: W) -> Self {
        HashingWriter {
            inner,
            hasher: Box::new(Xxh3Default::new()),
            written: 0,
        }
    }

    /// Bytes written so far.
    pub fn written(&self) -> u64 {
        self.written
    }

    /// Flush and return the inner writer, the byte count and the checksum.
    pub fn finish(mut self) -> io::Result<(W, u64, u64)> {
        self.inner.flush()?;
        Ok((self.inner, self.written, self.hasher.digest()))
    }
}

impl<W: Write> Write for HashingWriter<W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.hasher.update(&buf[..n]);
        self.written += n as u64;
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}

/// A reader that hashes every byte it hands out, so a file is verified in the same pass
/// that decodes it (one read of the file, no second buffer of its size).
pub struct HashingReader<R> {
    inner: R,
    hasher: Box<Xxh3Default>,
    read: u64,
}

impl<R: Read> HashingReader<R> {
    pub fn new(inner: R) -> Self {
        HashingReader {
            inner,
            hasher: Box::new(Xxh3Default::new()),
            read: 0,
        }
    }

    /// Bytes read so far.
    pub fn bytes_read(&self) -> u64 {
        self.read
    }

    /// The checksum of everything read so far.
    pub fn digest(&self) -> u64 {
        self.hasher.digest()
    }
}

impl<R: Read> Read for HashingReader<R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.hasher.update(&buf[..n]);
        self.read += n as u64;
        Ok(n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hex_round_trip_and_rejects() {
        for v in [0, 1, u64::MAX, 0x0123_4567_89ab_cdef] {
            assert_eq!(from_hex(&to_hex(v)), Some(v));
        }
        assert_eq!(from_hex("123"), None);
        assert_eq!(from_hex("+123456789abcdef"), None);
        assert_eq!(from_hex("0123456789abcdeg"), None);
    }

    #[test]
    fn streaming_matches_one_shot() {
        let data: Vec<u8> = (0..100_000u32).map(|i| (i * 7 + i / 13) as u8).collect();
        let mut w = HashingWriter::new(Vec::new());
        for chunk in data.chunks(777) {
            w.write_all(chunk).unwrap();
        }
        let (out, n, sum) = w.finish().unwrap();
        assert_eq!(out, data);
        assert_eq!(n, data.len() as u64);
        assert_eq!(sum, checksum(&data));

        let mut r = HashingReader::new(&data[..]);
        let mut back = Vec::new();
        r.read_to_end(&mut back).unwrap();
        assert_eq!(r.bytes_read(), data.len() as u64);
        assert_eq!(r.digest(), checksum(&data));
    }
}
