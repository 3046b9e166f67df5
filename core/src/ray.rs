//! A ray in flight between domains: [`RayRecord`], the self-contained ray with its
//! credit, and its wire form (format 2, 32 to 64 bytes a ray), carried by
//! `RayBatch.records` and `CacheLookups.records`.
//!
//! The in-memory ray belongs to the engine, not to the protocol crate: the tracer makes
//! and consumes it; the gRPC layer only moves its bytes.
//!
//! Format 2 is lossless and variable-length: a 4-byte header says which of the
//! optional fields follow and how many bytes each integer takes, so a ray pays only for
//! what it carries (format 1 was a fixed 64 bytes: a shadow ray's credit of 1 took 8
//! bytes, `tmax = +inf` and `bsdf_pdf = 0` 4 bytes each, a grey throughput 12). Floats
//! still travel bit-exact: the image must have the same bits in every configuration, and
//! a quantised direction or origin would move hit points. The authoritative table is in
//! `rays.proto`; in short, little-endian:
//!
//! | bytes   | field                                            | when            |
//! |--------:|--------------------------------------------------|-----------------|
//! | 4       | header (kind, flags, presence bits, lengths, depth) | always       |
//! | 0-8     | `credit`, its significant bytes                  | always          |
//! | 0-4     | `pixel`, its significant bytes                   | always          |
//! | 0-4     | `sample`, its significant bytes                  | always          |
//! | 12      | `origin`                                         | always          |
//! | 12      | `dir`                                            | always          |
//! | 4       | `tmax`                                           | unless `+inf`   |
//! | 4 or 12 | `weight`: one f32 when r, g, b have the same bits | always         |
//! | 4       | `bsdf_pdf`                                       | unless `+0.0`   |
//!
//! Every record has exactly one encoding (lengths are minimal, an omitted field is never
//! also written out), so decoding then encoding gives the same bytes. Decoding never
//! panics: a batch whose bytes do not hold exactly its `count` records, an unknown kind,
//! reserved header bits, a length out of range, a non-minimal encoding, a non-finite
//! origin or direction or a NaN `tmax` is an error naming the record.
//!
//! The job, the destination domain and the routing version are the same for every ray
//! of a batch and live in the `RayBatch` header, not here.

use crate::credit::Credit;
use crate::integrator::{RayKind, RayState};
use glam::Vec3;

/// The most bytes one ray takes on the wire (every optional field present, every
/// integer at full width); what memory budgets reserve per ray in flight.
pub const RAY_RECORD_MAX_BYTES: usize = 64;

/// The fewest bytes one ray takes on the wire: header, origin, direction, a grey weight.
pub const RAY_RECORD_MIN_BYTES: usize = 32;

/// The record format this module reads and writes (`RayStreamOpen.record_format`).
pub const RAY_RECORD_FORMAT: u32 = 2;

/// The deepest ray a record holds (11 bits; a job's `max_depth` is at most 1024).
pub const MAX_RECORD_DEPTH: u16 = 0x7ff;

/// `flags` bit 0: the ray carries a ray-cache ticket, found in `RayBatch.tickets`.
pub const FLAG_TICKETED: u8 = 1;

/// `flags` bit 1: the ray belongs to a ray-cache coarse pass: its `pixel` indexes the
/// coarse image, its contributions fill cache tickets only, never the image.
pub const FLAG_COARSE: u8 = 2;

/// `flags` bit 2: a probability hit map asked for this ray's outcome in the domain it
/// enters: the domain's owner reports whether it hit there.
pub const FLAG_PROBE: u8 = 4;

/// Flag bits this format defines; they are all the header's flag field holds.
const KNOWN_FLAGS: u8 = FLAG_TICKETED | FLAG_COARSE | FLAG_PROBE;

// The header, a little-endian u32: bits 0-2 kind, 3-5 flags, then presence bits, the
// byte lengths of the three integers, the depth, and two reserved bits.
const H_FLAGS_SHIFT: u32 = 3;
/// `tmax` is `+inf` and not written.
const H_TMAX_INF: u32 = 1 << 6;
/// `bsdf_pdf` is `+0.0` and not written.
const H_PDF_ZERO: u32 = 1 << 7;
/// `weight` is grey (r, g and b have the same bits): one f32 is written.
const H_GREY: u32 = 1 << 8;
const H_CREDIT_SHIFT: u32 = 9; // 4 bits, 0..=8
const H_PIXEL_SHIFT: u32 = 13; // 3 bits, 0..=4
const H_SAMPLE_SHIFT: u32 = 16; // 3 bits, 0..=4
const H_DEPTH_SHIFT: u32 = 19; // 11 bits
const H_RESERVED: u32 = 0b11 << 30;

const _: () = assert!(
    4 + 8 + 4 + 4 + 12 + 12 + 4 + 12 + 4 == RAY_RECORD_MAX_BYTES
        && 4 + 12 + 12 + 4 == RAY_RECORD_MIN_BYTES
);

/// One ray as it travels between actors: [`RayState`] plus what only the distributed
/// runtime needs (its credit share and flags).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayRecord {
    /// This ray's share of its tile's credit.
    pub credit: Credit,
    /// Ray origin, world space.
    pub origin: Vec3,
    /// Ray direction, world space.
    pub dir: Vec3,
    /// Far end of the ray's interval.
    pub tmax: f32,
    /// Path throughput; for shadow and AO rays, the contribution added if unoccluded.
    pub weight: Vec3,
    /// Solid-angle pdf of the BSDF sample that made this ray (0: no MIS).
    pub bsdf_pdf: f32,
    /// `y * width + x`.
    pub pixel: u32,
    /// Sample index within the pixel.
    pub sample: u32,
    /// Surface interactions before this ray; at most [`MAX_RECORD_DEPTH`]
    /// ([`RayRecord::from_state`] checks it).
    pub depth: u16,
    /// What the ray is for.
    pub kind: RayKind,
    /// [`FLAG_TICKETED`], [`FLAG_COARSE`], [`FLAG_PROBE`] or 0.
    pub flags: u8,
}

/// Why a batch of records could not be decoded (or a ray could not be packed).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RecordError {
    #[error("ray batch of {len} bytes ends inside record {index} (truncated)")]
    Truncated { len: usize, index: usize },
    #[error(
        "ray batch of {len} bytes cannot hold {count} records \
         ({RAY_RECORD_MIN_BYTES} to {RAY_RECORD_MAX_BYTES} bytes each)"
    )]
    Count { count: usize, len: usize },
    #[error("ray batch has {extra} bytes after its {count} records")]
    Trailing { count: usize, extra: usize },
    #[error("ray record {index}: unknown ray kind {kind}")]
    UnknownKind { index: usize, kind: u8 },
    #[error("ray record {index}: reserved header bits set ({header:#010x})")]
    ReservedBits { index: usize, header: u32 },
    #[error("ray record {index}: {field} length {bytes} is out of range")]
    BadLength {
        index: usize,
        field: &'static str,
        bytes: u32,
    },
    #[error("ray record {index}: {field} is not in its one (shortest) encoding")]
    NonCanonical { index: usize, field: &'static str },
    #[error("ray record {index}: non-finite {field}")]
    NonFinite { index: usize, field: &'static str },
    #[error("ray record {index}: tmax is NaN")]
    NanTmax { index: usize },
    #[error("ray depth {depth} does not fit the record's 11 bits (at most {MAX_RECORD_DEPTH})")]
    DepthTooLarge { depth: u32 },
}

impl RayRecord {
    /// Pack a core ray with its credit share. Fails only for a depth beyond
    /// [`MAX_RECORD_DEPTH`], which no valid job reaches (max_depth is at most 1024).
    pub fn from_state(ray: &RayState, credit: Credit) -> Result<RayRecord, RecordError> {
        let depth = u16::try_from(ray.depth)
            .ok()
            .filter(|&d| d <= MAX_RECORD_DEPTH)
            .ok_or(RecordError::DepthTooLarge { depth: ray.depth })?;
        Ok(RayRecord {
            credit,
            origin: ray.origin,
            dir: ray.dir,
            tmax: ray.tmax,
            weight: ray.weight,
            bsdf_pdf: ray.bsdf_pdf,
            pixel: ray.pixel,
            sample: ray.sample,
            depth,
            kind: ray.kind,
            flags: 0,
        })
    }

    /// The core ray (credit and flags stay with the record).
    pub fn to_state(&self) -> RayState {
        RayState {
            origin: self.origin,
            dir: self.dir,
            tmax: self.tmax,
            pixel: self.pixel,
            sample: self.sample,
            depth: u32::from(self.depth),
            kind: self.kind,
            weight: self.weight,
            bsdf_pdf: self.bsdf_pdf,
        }
    }

    /// Whether the ray carries a ray-cache ticket.
    pub fn is_ticketed(&self) -> bool {
        self.flags & FLAG_TICKETED != 0
    }

    fn tmax_inf(&self) -> bool {
        self.tmax.to_bits() == f32::INFINITY.to_bits()
    }

    fn pdf_zero(&self) -> bool {
        self.bsdf_pdf.to_bits() == 0
    }

    fn grey(&self) -> bool {
        let w = self.weight;
        w.x.to_bits() == w.y.to_bits() && w.y.to_bits() == w.z.to_bits()
    }

    /// Bytes this ray takes on the wire ([`RAY_RECORD_MIN_BYTES`] to
    /// [`RAY_RECORD_MAX_BYTES`]): what `ray_bytes_sent` counts.
    pub fn encoded_len(&self) -> usize {
        RAY_RECORD_MIN_BYTES
            + uint_len(self.credit.to_wire())
            + uint_len(u64::from(self.pixel))
            + uint_len(u64::from(self.sample))
            + if self.tmax_inf() { 0 } else { 4 }
            + if self.grey() { 0 } else { 8 }
            + if self.pdf_zero() { 0 } else { 4 }
    }

    /// Write the record into `b`; returns its length. The depth is masked to 11 bits
    /// (a record made by [`RayRecord::from_state`] or decoded always fits).
    fn pack(&self, b: &mut [u8; RAY_RECORD_MAX_BYTES]) -> usize {
        debug_assert!(self.depth <= MAX_RECORD_DEPTH, "depth {}", self.depth);
        debug_assert!(self.flags & !KNOWN_FLAGS == 0, "flags {:#x}", self.flags);
        let credit = self.credit.to_wire();
        let (cl, pl, sl) = (
            uint_len(credit),
            uint_len(u64::from(self.pixel)),
            uint_len(u64::from(self.sample)),
        );
        let (tmax_inf, pdf_zero, grey) = (self.tmax_inf(), self.pdf_zero(), self.grey());
        let mut header = self.kind as u32
            | u32::from(self.flags & KNOWN_FLAGS) << H_FLAGS_SHIFT
            | (cl as u32) << H_CREDIT_SHIFT
            | (pl as u32) << H_PIXEL_SHIFT
            | (sl as u32) << H_SAMPLE_SHIFT
            | u32::from(self.depth & MAX_RECORD_DEPTH) << H_DEPTH_SHIFT;
        if tmax_inf {
            header |= H_TMAX_INF;
        }
        if pdf_zero {
            header |= H_PDF_ZERO;
        }
        if grey {
            header |= H_GREY;
        }
        let mut w = Writer { b, pos: 0 };
        w.put(&header.to_le_bytes());
        w.put(&credit.to_le_bytes()[..cl]);
        w.put(&self.pixel.to_le_bytes()[..pl]);
        w.put(&self.sample.to_le_bytes()[..sl]);
        w.vec3(self.origin);
        w.vec3(self.dir);
        if !tmax_inf {
            w.put(&self.tmax.to_le_bytes());
        }
        if grey {
            w.put(&self.weight.x.to_le_bytes());
        } else {
            w.vec3(self.weight);
        }
        if !pdf_zero {
            w.put(&self.bsdf_pdf.to_le_bytes());
        }
        w.pos
    }

    /// Append the record's bytes to `out`.
    pub fn write_to(&self, out: &mut Vec<u8>) {
        let mut b = [0u8; RAY_RECORD_MAX_BYTES];
        let n = self.pack(&mut b);
        out.extend_from_slice(&b[..n]);
    }

    /// The record's bytes.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(RAY_RECORD_MAX_BYTES);
        self.write_to(&mut out);
        out
    }

    /// Read the record at the start of `bytes`; returns it and its length. `index` only
    /// names it in errors, `len` (the whole batch's length) only in a truncation error.
    fn read(bytes: &[u8], index: usize, len: usize) -> Result<(RayRecord, usize), RecordError> {
        let mut r = Reader {
            b: bytes,
            pos: 0,
            index,
            len,
        };
        let header = u32::from_le_bytes(r.take::<4>()?);
        if header & H_RESERVED != 0 {
            return Err(RecordError::ReservedBits { index, header });
        }
        let kind_code = (header & 0b111) as u8;
        let kind = *RayKind::ALL
            .get(usize::from(kind_code))
            .ok_or(RecordError::UnknownKind {
                index,
                kind: kind_code,
            })?;
        let flags = ((header >> H_FLAGS_SHIFT) & 0b111) as u8;
        let credit = r.uint((header >> H_CREDIT_SHIFT) & 0b1111, 8, "credit")?;
        let pixel = r.uint((header >> H_PIXEL_SHIFT) & 0b111, 4, "pixel")? as u32;
        let sample = r.uint((header >> H_SAMPLE_SHIFT) & 0b111, 4, "sample")? as u32;
        let depth = (header >> H_DEPTH_SHIFT) as u16 & MAX_RECORD_DEPTH;
        let origin = r.vec3()?;
        if !origin.is_finite() {
            return Err(RecordError::NonFinite {
                index,
                field: "origin",
            });
        }
        let dir = r.vec3()?;
        if !dir.is_finite() {
            return Err(RecordError::NonFinite {
                index,
                field: "direction",
            });
        }
        let tmax = if header & H_TMAX_INF != 0 {
            f32::INFINITY
        } else {
            let t = r.f32()?;
            if t.is_nan() {
                return Err(RecordError::NanTmax { index });
            }
            if t.to_bits() == f32::INFINITY.to_bits() {
                return Err(RecordError::NonCanonical {
                    index,
                    field: "tmax",
                });
            }
            t
        };
        let weight = if header & H_GREY != 0 {
            Vec3::splat(r.f32()?)
        } else {
            let w = r.vec3()?;
            if w.x.to_bits() == w.y.to_bits() && w.y.to_bits() == w.z.to_bits() {
                return Err(RecordError::NonCanonical {
                    index,
                    field: "weight",
                });
            }
            w
        };
        let bsdf_pdf = if header & H_PDF_ZERO != 0 {
            0.0
        } else {
            let p = r.f32()?;
            if p.to_bits() == 0 {
                return Err(RecordError::NonCanonical {
                    index,
                    field: "bsdf_pdf",
                });
            }
            p
        };
        let rec = RayRecord {
            credit: Credit::from_wire(credit),
            origin,
            dir,
            tmax,
            weight,
            bsdf_pdf,
            pixel,
            sample,
            depth,
            kind,
            flags,
        };
        Ok((rec, r.pos))
    }
}

/// Significant bytes of `v`: 0 for 0, else up to 8.
#[inline]
fn uint_len(v: u64) -> usize {
    (64 - v.leading_zeros() as usize).div_ceil(8)
}

/// Fills a record's buffer front to back (the buffer always has room: 64 bytes is the
/// largest record).
struct Writer<'a> {
    b: &'a mut [u8; RAY_RECORD_MAX_BYTES],
    pos: usize,
}

impl Writer<'_> {
    #[inline]
    fn put(&mut self, src: &[u8]) {
        self.b[self.pos..self.pos + src.len()].copy_from_slice(src);
        self.pos += src.len();
    }

    #[inline]
    fn vec3(&mut self, v: Vec3) {
        self.put(&v.x.to_le_bytes());
        self.put(&v.y.to_le_bytes());
        self.put(&v.z.to_le_bytes());
    }
}

/// Reads one record's fields, failing with `Truncated` where the bytes run out.
struct Reader<'a> {
    b: &'a [u8],
    pos: usize,
    index: usize,
    len: usize,
}

impl Reader<'_> {
    #[inline]
    fn take<const N: usize>(&mut self) -> Result<[u8; N], RecordError> {
        let end = self.pos + N;
        let s = self.b.get(self.pos..end).ok_or(RecordError::Truncated {
            len: self.len,
            index: self.index,
        })?;
        self.pos = end;
        Ok(s.try_into().expect("N bytes"))
    }

    /// A little-endian integer of `n` bytes (at most `max`), in its shortest form.
    #[inline]
    fn uint(&mut self, n: u32, max: u32, field: &'static str) -> Result<u64, RecordError> {
        if n > max {
            return Err(RecordError::BadLength {
                index: self.index,
                field,
                bytes: n,
            });
        }
        let n = n as usize;
        let s = self
            .b
            .get(self.pos..self.pos + n)
            .ok_or(RecordError::Truncated {
                len: self.len,
                index: self.index,
            })?;
        if s.last() == Some(&0) {
            return Err(RecordError::NonCanonical {
                index: self.index,
                field,
            });
        }
        self.pos += n;
        let mut v = [0u8; 8];
        v[..n].copy_from_slice(s);
        Ok(u64::from_le_bytes(v))
    }

    #[inline]
    fn f32(&mut self) -> Result<f32, RecordError> {
        Ok(f32::from_le_bytes(self.take::<4>()?))
    }

    #[inline]
    fn vec3(&mut self) -> Result<Vec3, RecordError> {
        Ok(Vec3::new(self.f32()?, self.f32()?, self.f32()?))
    }
}

/// Append the records of `rays` to `out`.
pub fn encode_rays(rays: &[RayRecord], out: &mut Vec<u8>) {
    out.reserve(rays.len() * RAY_RECORD_MAX_BYTES);
    let mut b = [0u8; RAY_RECORD_MAX_BYTES];
    for r in rays {
        let n = r.pack(&mut b);
        out.extend_from_slice(&b[..n]);
    }
}

/// Bytes the records of `rays` take on the wire.
pub fn encoded_len(rays: &[RayRecord]) -> usize {
    rays.iter().map(RayRecord::encoded_len).sum()
}

/// Whether `len` bytes can hold `count` records at all (each takes
/// [`RAY_RECORD_MIN_BYTES`] to [`RAY_RECORD_MAX_BYTES`]): a receiver's cheap check of a
/// batch's `count` against its bytes before it decodes or grants anything. Returns the
/// count.
pub fn check_count(count: u64, len: usize) -> Result<usize, RecordError> {
    let bad = || RecordError::Count {
        count: usize::try_from(count).unwrap_or(usize::MAX),
        len,
    };
    let n = usize::try_from(count).map_err(|_| bad())?;
    let min = n.checked_mul(RAY_RECORD_MIN_BYTES).ok_or_else(bad)?;
    let max = n.checked_mul(RAY_RECORD_MAX_BYTES).ok_or_else(bad)?;
    if len < min || len > max {
        return Err(bad());
    }
    Ok(n)
}

/// Read the `count` records of a batch. Any malformed record fails the whole batch,
/// naming the record, and so do bytes left over; nothing here panics on any input.
pub fn decode_rays(bytes: &[u8], count: usize) -> Result<Vec<RayRecord>, RecordError> {
    check_count(count as u64, bytes.len())?;
    let mut out = Vec::with_capacity(count);
    decode_rays_into(bytes, count, &mut out)?;
    Ok(out)
}

/// Like [`decode_rays`], appending to `out` (reuse a buffer across batches). On error
/// `out` is left as it was.
pub fn decode_rays_into(
    bytes: &[u8],
    count: usize,
    out: &mut Vec<RayRecord>,
) -> Result<(), RecordError> {
    check_count(count as u64, bytes.len())?;
    let start = out.len();
    out.reserve(count);
    let mut pos = 0;
    for index in 0..count {
        match RayRecord::read(&bytes[pos..], index, bytes.len()) {
            Ok((r, n)) => {
                out.push(r);
                pos += n;
            }
            Err(e) => {
                out.truncate(start);
                return Err(e);
            }
        }
    }
    if pos != bytes.len() {
        out.truncate(start);
        return Err(RecordError::Trailing {
            count,
            extra: bytes.len() - pos,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// SplitMix64: a tiny deterministic generator, so the tests need no extra crates.
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        }
        fn u32(&mut self) -> u32 {
            self.next() as u32
        }
        /// Any finite f32, including subnormals, zeros of both signs and extremes.
        fn finite(&mut self) -> f32 {
            loop {
                let f = f32::from_bits(self.u32());
                if f.is_finite() {
                    return f;
                }
            }
        }
        fn finite3(&mut self) -> Vec3 {
            Vec3::new(self.finite(), self.finite(), self.finite())
        }
        /// Any bit pattern at all (NaN payloads, infinities) for fields that allow it.
        fn any_bits3(&mut self) -> Vec3 {
            Vec3::new(
                f32::from_bits(self.u32()),
                f32::from_bits(self.u32()),
                f32::from_bits(self.u32()),
            )
        }
        /// An integer of 0 to 64 significant bits, so every length is exercised.
        fn sized(&mut self) -> u64 {
            let bits = self.next() % 65;
            if bits == 0 {
                0
            } else {
                self.next() >> (64 - bits)
            }
        }
    }

    fn random_record(rng: &mut Rng) -> RayRecord {
        let tmax = match rng.next() % 4 {
            0 => f32::INFINITY,
            _ => rng.finite(),
        };
        let weight = match rng.next() % 3 {
            0 => Vec3::splat(f32::from_bits(rng.u32())),
            _ => rng.any_bits3(),
        };
        RayRecord {
            credit: Credit::from_wire(rng.sized()),
            origin: rng.finite3(),
            dir: rng.finite3(),
            tmax,
            weight,
            bsdf_pdf: match rng.next() % 3 {
                0 => 0.0,
                _ => f32::from_bits(rng.u32()),
            },
            pixel: rng.sized() as u32,
            sample: rng.sized() as u32,
            depth: rng.next() as u16 & MAX_RECORD_DEPTH,
            kind: RayKind::ALL[(rng.next() % RayKind::COUNT as u64) as usize],
            flags: (rng.next() as u8) & KNOWN_FLAGS,
        }
    }

    fn same_bits(a: &RayRecord, b: &RayRecord) -> bool {
        let v = |v: Vec3| [v.x.to_bits(), v.y.to_bits(), v.z.to_bits()];
        a.credit == b.credit
            && v(a.origin) == v(b.origin)
            && v(a.dir) == v(b.dir)
            && a.tmax.to_bits() == b.tmax.to_bits()
            && v(a.weight) == v(b.weight)
            && a.bsdf_pdf.to_bits() == b.bsdf_pdf.to_bits()
            && a.pixel == b.pixel
            && a.sample == b.sample
            && a.depth == b.depth
            && a.kind == b.kind
            && a.flags == b.flags
    }

    #[test]
    fn records_take_32_to_64_bytes() {
        let mut rng = Rng(1);
        for _ in 0..2000 {
            let r = random_record(&mut rng);
            let n = r.to_bytes().len();
            assert_eq!(n, r.encoded_len());
            assert!((RAY_RECORD_MIN_BYTES..=RAY_RECORD_MAX_BYTES).contains(&n));
        }
        let full = RayRecord {
            credit: Credit::from_wire(u64::MAX),
            origin: Vec3::ONE,
            dir: Vec3::ONE,
            tmax: 1.0,
            weight: Vec3::new(1.0, 2.0, 3.0),
            bsdf_pdf: 1.0,
            pixel: u32::MAX,
            sample: u32::MAX,
            depth: MAX_RECORD_DEPTH,
            kind: RayKind::Diffuse,
            flags: KNOWN_FLAGS,
        };
        assert_eq!(full.encoded_len(), RAY_RECORD_MAX_BYTES);
        let least = RayRecord {
            credit: Credit::ZERO,
            tmax: f32::INFINITY,
            weight: Vec3::ONE,
            bsdf_pdf: 0.0,
            pixel: 0,
            sample: 0,
            ..full
        };
        assert_eq!(least.encoded_len(), RAY_RECORD_MIN_BYTES);
    }

    #[test]
    fn round_trip_is_bit_exact() {
        let mut rng = Rng(0x5eed);
        for n in [0usize, 1, 2, 7, 1000] {
            let rays: Vec<RayRecord> = (0..n).map(|_| random_record(&mut rng)).collect();
            let mut bytes = Vec::new();
            encode_rays(&rays, &mut bytes);
            assert_eq!(bytes.len(), encoded_len(&rays));
            let back = decode_rays(&bytes, n).unwrap();
            assert_eq!(back.len(), n);
            for (a, b) in rays.iter().zip(&back) {
                assert!(same_bits(a, b), "{a:?} != {b:?}");
                assert_eq!(a.to_bytes(), b.to_bytes());
            }
            // Re-encoding gives the same bytes: one encoding per record.
            let mut again = Vec::new();
            encode_rays(&back, &mut again);
            assert_eq!(bytes, again);
        }
    }

    #[test]
    fn layout_is_as_documented() {
        // A shadow ray as a path tracer sends it: credit 1, grey weight, no MIS pdf.
        let r = RayRecord {
            credit: Credit::from_wire(1),
            origin: Vec3::new(1.0, 2.0, 3.0),
            dir: Vec3::new(-1.0, 0.5, 0.25),
            tmax: 0.5,
            weight: Vec3::splat(0.1),
            bsdf_pdf: 0.0,
            pixel: 0x01_beef,
            sample: 42,
            depth: 0x304,
            kind: RayKind::Shadow,
            flags: FLAG_TICKETED,
        };
        let b = r.to_bytes();
        let header = 1 | 1 << 3 | H_PDF_ZERO | H_GREY | 1 << 9 | 3 << 13 | 1 << 16 | 0x304 << 19;
        assert_eq!(&b[0..4], &header.to_le_bytes());
        assert_eq!(b[4], 1, "credit");
        assert_eq!(&b[5..8], &[0xef, 0xbe, 0x01], "pixel");
        assert_eq!(b[8], 42, "sample");
        assert_eq!(&b[9..13], &1.0f32.to_le_bytes());
        assert_eq!(&b[17..21], &3.0f32.to_le_bytes());
        assert_eq!(&b[21..25], &(-1.0f32).to_le_bytes());
        assert_eq!(&b[33..37], &0.5f32.to_le_bytes(), "tmax");
        assert_eq!(&b[37..41], &0.1f32.to_le_bytes(), "grey weight");
        assert_eq!(b.len(), 41);
        assert!(r.is_ticketed());

        // A diffuse bounce: tmax +inf left out, a coloured weight and a pdf written.
        let d = RayRecord {
            kind: RayKind::Diffuse,
            flags: 0,
            tmax: f32::INFINITY,
            weight: Vec3::new(0.1, 0.2, 0.3),
            bsdf_pdf: 0.75,
            credit: Credit::from_wire(0x0102_0304_0506),
            ..r
        };
        let b = d.to_bytes();
        let h = u32::from_le_bytes(b[0..4].try_into().unwrap());
        assert_eq!(h & 7, 4);
        assert_eq!(h & (H_TMAX_INF | H_PDF_ZERO | H_GREY), H_TMAX_INF);
        assert_eq!(&b[4..10], &[6, 5, 4, 3, 2, 1], "credit");
        assert_eq!(&b[38..42], &0.1f32.to_le_bytes());
        assert_eq!(&b[46..50], &0.3f32.to_le_bytes());
        assert_eq!(&b[50..54], &0.75f32.to_le_bytes(), "bsdf_pdf");
        assert_eq!(b.len(), 54);
    }

    #[test]
    fn every_partial_length_is_an_error() {
        let mut rng = Rng(7);
        let rays: Vec<RayRecord> = (0..4).map(|_| random_record(&mut rng)).collect();
        let mut bytes = Vec::new();
        encode_rays(&rays, &mut bytes);
        let mut ends = vec![0];
        for r in &rays {
            ends.push(ends.last().unwrap() + r.encoded_len());
        }
        for len in 0..=bytes.len() {
            let whole = ends.iter().position(|&e| e == len);
            for count in 0..=4 {
                let res = decode_rays(&bytes[..len], count);
                if whole == Some(count) {
                    assert_eq!(res.unwrap().len(), count);
                } else {
                    let err = res.unwrap_err();
                    assert!(
                        matches!(
                            err,
                            RecordError::Truncated { .. }
                                | RecordError::Count { .. }
                                | RecordError::Trailing { .. }
                        ),
                        "{len} bytes, {count} records: {err}"
                    );
                }
            }
        }
        // A misaligned start (one byte dropped at the front) is caught too.
        assert!(decode_rays(&bytes[1..], 4).is_err());
        assert!(decode_rays(&bytes, 5).is_err());
    }

    #[test]
    fn bad_fields_name_the_record() {
        // Three records with every optional field written (non-grey weight, finite tmax,
        // a pdf) and full-width integers, so offsets are fixed.
        let mut rng = Rng(9);
        let rays: Vec<RayRecord> = (0..3)
            .map(|_| {
                let mut r = random_record(&mut rng);
                r.tmax = 1.0;
                r.weight = Vec3::new(0.1, 0.2, 0.3);
                r.bsdf_pdf = 0.5;
                r.credit = Credit::from_wire(u64::MAX);
                r.pixel = u32::MAX;
                r.sample = u32::MAX;
                r
            })
            .collect();
        let mut good = Vec::new();
        encode_rays(&rays, &mut good);
        assert_eq!(good.len(), 3 * RAY_RECORD_MAX_BYTES);
        let base = 2 * RAY_RECORD_MAX_BYTES;
        let header = |b: &[u8]| u32::from_le_bytes(b[base..base + 4].try_into().unwrap());
        let set_header =
            |b: &mut Vec<u8>, h: u32| b[base..base + 4].copy_from_slice(&h.to_le_bytes());

        let mut b = good.clone();
        let h = header(&b);
        set_header(&mut b, (h & !7) | RayKind::COUNT as u32);
        assert_eq!(
            decode_rays(&b, 3).unwrap_err(),
            RecordError::UnknownKind { index: 2, kind: 6 }
        );
        set_header(&mut b, h | 7);
        let msg = decode_rays(&b, 3).unwrap_err().to_string();
        assert!(msg.contains("record 2") && msg.contains('7'), "{msg}");

        let mut b = good.clone();
        set_header(&mut b, h | 1 << 31);
        assert_eq!(
            decode_rays(&b, 3).unwrap_err(),
            RecordError::ReservedBits {
                index: 2,
                header: h | 1 << 31
            }
        );

        let mut b = good.clone();
        set_header(
            &mut b,
            (h & !(0b1111 << H_CREDIT_SHIFT)) | 9 << H_CREDIT_SHIFT,
        );
        assert_eq!(
            decode_rays(&b, 3).unwrap_err(),
            RecordError::BadLength {
                index: 2,
                field: "credit",
                bytes: 9
            }
        );
        let mut b = good.clone();
        set_header(&mut b, (h & !(0b111 << H_PIXEL_SHIFT)) | 5 << H_PIXEL_SHIFT);
        assert!(matches!(
            decode_rays(&b, 3).unwrap_err(),
            RecordError::BadLength {
                index: 2,
                field: "pixel",
                bytes: 5
            }
        ));

        // Non-minimal forms: a zero top byte of the credit, an omitted-value written out.
        let mut b = good.clone();
        b[base + 4 + 7] = 0;
        assert_eq!(
            decode_rays(&b, 3).unwrap_err(),
            RecordError::NonCanonical {
                index: 2,
                field: "credit"
            }
        );
        // Offsets in a full record: header 4, credit 8, pixel 4, sample 4, origin 12,
        // dir 12, tmax 4, weight 12, pdf 4.
        let (origin, dir, tmax, weight, pdf) = (20, 32, 44, 48, 60);
        let mut b = good.clone();
        b[base + tmax..base + tmax + 4].copy_from_slice(&f32::INFINITY.to_le_bytes());
        assert_eq!(
            decode_rays(&b, 3).unwrap_err(),
            RecordError::NonCanonical {
                index: 2,
                field: "tmax"
            }
        );
        let mut b = good.clone();
        for k in 0..3 {
            let at = base + weight + 4 * k;
            b[at..at + 4].copy_from_slice(&0.1f32.to_le_bytes());
        }
        assert_eq!(
            decode_rays(&b, 3).unwrap_err(),
            RecordError::NonCanonical {
                index: 2,
                field: "weight"
            }
        );
        let mut b = good.clone();
        b[base + pdf..base + pdf + 4].copy_from_slice(&0.0f32.to_le_bytes());
        assert_eq!(
            decode_rays(&b, 3).unwrap_err(),
            RecordError::NonCanonical {
                index: 2,
                field: "bsdf_pdf"
            }
        );

        for (offset, field) in [
            (origin, "origin"),
            (origin + 8, "origin"),
            (dir, "direction"),
            (dir + 8, "direction"),
        ] {
            for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
                let mut b = good.clone();
                b[base + offset..base + offset + 4].copy_from_slice(&bad.to_le_bytes());
                assert_eq!(
                    decode_rays(&b, 3).unwrap_err(),
                    RecordError::NonFinite { index: 2, field }
                );
            }
        }

        let mut b = good.clone();
        b[base + tmax..base + tmax + 4].copy_from_slice(&f32::NAN.to_le_bytes());
        assert_eq!(
            decode_rays(&b, 3).unwrap_err(),
            RecordError::NanTmax { index: 2 }
        );

        // decode_rays_into leaves the output untouched on error.
        let mut out = vec![rays[0]];
        assert!(decode_rays_into(&b, 3, &mut out).is_err());
        assert_eq!(out.len(), 1);
    }

    #[test]
    fn counts_that_cannot_fit_are_refused_before_decoding() {
        assert_eq!(check_count(2, 64), Ok(2));
        assert_eq!(check_count(2, 128), Ok(2));
        assert!(check_count(2, 63).is_err());
        assert!(check_count(2, 129).is_err());
        assert!(check_count(u64::MAX, 1 << 20).is_err());
        let msg = check_count(3, 10).unwrap_err().to_string();
        assert!(
            msg.contains("10 bytes") && msg.contains("3 records"),
            "{msg}"
        );
    }

    #[test]
    fn garbage_never_panics() {
        let mut rng = Rng(3);
        for len in 0..300 {
            let bytes: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
            for count in 0..6 {
                let _ = decode_rays(&bytes, count);
            }
        }
    }

    #[test]
    fn core_ray_round_trip() {
        let ray = RayState {
            origin: Vec3::new(1e6, -2.5, 0.125),
            dir: Vec3::new(0.0, -1.0, 0.0),
            tmax: 17.5,
            pixel: 640 * 479 + 639,
            sample: 65535,
            depth: 1024,
            kind: RayKind::Shadow,
            weight: Vec3::new(0.5, 0.25, 2.0),
            bsdf_pdf: 0.0,
        };
        let rec = RayRecord::from_state(&ray, Credit::from_wire(1 << 40)).unwrap();
        assert_eq!(rec.credit, Credit::from_wire(1 << 40));
        assert!(!rec.is_ticketed());
        let back = decode_rays(&rec.to_bytes(), 1).unwrap()[0].to_state();
        assert_eq!(back, ray);

        for depth in [u32::from(MAX_RECORD_DEPTH) + 1, 70_000] {
            let deep = RayState { depth, ..ray };
            assert_eq!(
                RayRecord::from_state(&deep, Credit::from_wire(1)),
                Err(RecordError::DepthTooLarge { depth })
            );
        }
    }
}
