//! A ray in flight between domains: [`RayRecord`], the self-contained ray with its
//! credit, and its 64-byte wire form (format 1), carried by `RayBatch.records`.
//!
//! The in-memory ray belongs to the engine, not to the protocol crate: the tracer makes
//! and consumes it; the gRPC layer only moves its bytes.
//!
//! Layout (little-endian, no padding; the authoritative table is in `rays.proto`):
//!
//! | offset | size | type    | field      |
//! |-------:|-----:|---------|------------|
//! |      0 |    8 | u64     | `credit`   |
//! |      8 |   12 | f32 x3  | `origin`   |
//! |     20 |   12 | f32 x3  | `dir`      |
//! |     32 |    4 | f32     | `tmax`     |
//! |     36 |   12 | f32 x3  | `weight`   |
//! |     48 |    4 | f32     | `bsdf_pdf` |
//! |     52 |    4 | u32     | `pixel`    |
//! |     56 |    4 | u32     | `sample`   |
//! |     60 |    2 | u16     | `depth`    |
//! |     62 |    1 | u8      | `kind`     |
//! |     63 |    1 | u8      | `flags`    |
//!
//! Floats travel bit-exact. Decoding never panics: a batch whose length is not a whole
//! number of records, an unknown kind, reserved flag bits, a non-finite origin or
//! direction or a NaN `tmax` is an error naming the record.
//!
//! The job, the destination domain and the routing version are the same for every ray
//! of a batch and live in the `RayBatch` header, not here.

use crate::credit::Credit;
use crate::integrator::{RayKind, RayState};
use glam::Vec3;

/// Bytes per ray on the wire.
pub const RAY_RECORD_BYTES: usize = 64;

/// The record format this module reads and writes (`RayStreamOpen.record_format`).
pub const RAY_RECORD_FORMAT: u32 = 1;

/// `flags` bit 0: the ray carries a ray-cache ticket, found in `RayBatch.tickets`.
pub const FLAG_TICKETED: u8 = 1;

/// `flags` bit 1: the ray belongs to a ray-cache coarse pass: its `pixel` indexes the
/// coarse image, its contributions fill cache tickets only, never the image.
pub const FLAG_COARSE: u8 = 2;

/// `flags` bit 2: a probability hit map asked for this ray's outcome in the domain it
/// enters: the domain's owner reports whether it hit there.
pub const FLAG_PROBE: u8 = 4;

/// Flag bits this format defines; any other bit set is an error.
const KNOWN_FLAGS: u8 = FLAG_TICKETED | FLAG_COARSE | FLAG_PROBE;

const _: () = assert!(RAY_RECORD_BYTES <= 64);

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
    /// Surface interactions before this ray.
    pub depth: u16,
    /// What the ray is for.
    pub kind: RayKind,
    /// [`FLAG_TICKETED`] or 0.
    pub flags: u8,
}

/// Why a batch of records could not be decoded (or a ray could not be packed).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RecordError {
    #[error(
        "ray batch of {len} bytes is not a whole number of {RAY_RECORD_BYTES}-byte records: \
         record {index} is truncated to {} bytes",
        len % RAY_RECORD_BYTES
    )]
    Truncated { len: usize, index: usize },
    #[error("ray record {index}: unknown ray kind {kind}")]
    UnknownKind { index: usize, kind: u8 },
    #[error("ray record {index}: reserved flag bits set ({flags:#04x})")]
    ReservedFlags { index: usize, flags: u8 },
    #[error("ray record {index}: non-finite {field}")]
    NonFinite { index: usize, field: &'static str },
    #[error("ray record {index}: tmax is NaN")]
    NanTmax { index: usize },
    #[error("ray depth {depth} does not fit the record's 16 bits")]
    DepthTooLarge { depth: u32 },
}

impl RayRecord {
    /// Pack a core ray with its credit share. Fails only for a depth beyond 16 bits,
    /// which no valid job reaches (max_depth is at most 1024).
    pub fn from_state(ray: &RayState, credit: Credit) -> Result<RayRecord, RecordError> {
        let depth = u16::try_from(ray.depth)
            .map_err(|_| RecordError::DepthTooLarge { depth: ray.depth })?;
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

    /// The record's bytes.
    pub fn to_bytes(&self) -> [u8; RAY_RECORD_BYTES] {
        let mut b = [0u8; RAY_RECORD_BYTES];
        b[0..8].copy_from_slice(&self.credit.to_wire().to_le_bytes());
        put_vec3(&mut b[8..20], self.origin);
        put_vec3(&mut b[20..32], self.dir);
        b[32..36].copy_from_slice(&self.tmax.to_le_bytes());
        put_vec3(&mut b[36..48], self.weight);
        b[48..52].copy_from_slice(&self.bsdf_pdf.to_le_bytes());
        b[52..56].copy_from_slice(&self.pixel.to_le_bytes());
        b[56..60].copy_from_slice(&self.sample.to_le_bytes());
        b[60..62].copy_from_slice(&self.depth.to_le_bytes());
        b[62] = self.kind as u8;
        b[63] = self.flags;
        b
    }

    /// Read one record; `index` only names it in errors.
    pub fn from_bytes(b: &[u8; RAY_RECORD_BYTES], index: usize) -> Result<RayRecord, RecordError> {
        let kind_code = b[62];
        let kind = *RayKind::ALL
            .get(usize::from(kind_code))
            .ok_or(RecordError::UnknownKind {
                index,
                kind: kind_code,
            })?;
        let flags = b[63];
        if flags & !KNOWN_FLAGS != 0 {
            return Err(RecordError::ReservedFlags { index, flags });
        }
        let origin = get_vec3(&b[8..20]);
        if !origin.is_finite() {
            return Err(RecordError::NonFinite {
                index,
                field: "origin",
            });
        }
        let dir = get_vec3(&b[20..32]);
        if !dir.is_finite() {
            return Err(RecordError::NonFinite {
                index,
                field: "direction",
            });
        }
        let tmax = get_f32(&b[32..36]);
        if tmax.is_nan() {
            return Err(RecordError::NanTmax { index });
        }
        Ok(RayRecord {
            credit: Credit::from_wire(u64::from_le_bytes(b[0..8].try_into().expect("8 bytes"))),
            origin,
            dir,
            tmax,
            weight: get_vec3(&b[36..48]),
            bsdf_pdf: get_f32(&b[48..52]),
            pixel: get_u32(&b[52..56]),
            sample: get_u32(&b[56..60]),
            depth: u16::from_le_bytes([b[60], b[61]]),
            kind,
            flags,
        })
    }
}

#[inline]
fn put_vec3(dst: &mut [u8], v: Vec3) {
    dst[0..4].copy_from_slice(&v.x.to_le_bytes());
    dst[4..8].copy_from_slice(&v.y.to_le_bytes());
    dst[8..12].copy_from_slice(&v.z.to_le_bytes());
}

#[inline]
fn get_u32(src: &[u8]) -> u32 {
    u32::from_le_bytes([src[0], src[1], src[2], src[3]])
}

#[inline]
fn get_f32(src: &[u8]) -> f32 {
    f32::from_bits(get_u32(src))
}

#[inline]
fn get_vec3(src: &[u8]) -> Vec3 {
    Vec3::new(
        get_f32(&src[0..4]),
        get_f32(&src[4..8]),
        get_f32(&src[8..12]),
    )
}

/// Append the records of `rays` to `out` (`rays.len() * RAY_RECORD_BYTES` bytes).
pub fn encode_rays(rays: &[RayRecord], out: &mut Vec<u8>) {
    out.reserve(rays.len() * RAY_RECORD_BYTES);
    for r in rays {
        out.extend_from_slice(&r.to_bytes());
    }
}

/// Number of whole records in a batch of `len` bytes, or the error for a partial one.
pub fn record_count(len: usize) -> Result<usize, RecordError> {
    if !len.is_multiple_of(RAY_RECORD_BYTES) {
        return Err(RecordError::Truncated {
            len,
            index: len / RAY_RECORD_BYTES,
        });
    }
    Ok(len / RAY_RECORD_BYTES)
}

/// Read every record of a batch. Any malformed record fails the whole batch, naming the
/// record; nothing here panics on any input.
pub fn decode_rays(bytes: &[u8]) -> Result<Vec<RayRecord>, RecordError> {
    let mut out = Vec::with_capacity(record_count(bytes.len())?);
    decode_rays_into(bytes, &mut out)?;
    Ok(out)
}

/// Like [`decode_rays`], appending to `out` (reuse a buffer across batches). On error
/// `out` is left as it was.
pub fn decode_rays_into(bytes: &[u8], out: &mut Vec<RayRecord>) -> Result<(), RecordError> {
    let n = record_count(bytes.len())?;
    let start = out.len();
    out.reserve(n);
    for (index, chunk) in bytes.chunks_exact(RAY_RECORD_BYTES).enumerate() {
        let chunk: &[u8; RAY_RECORD_BYTES] = chunk.try_into().expect("exact chunk");
        match RayRecord::from_bytes(chunk, index) {
            Ok(r) => out.push(r),
            Err(e) => {
                out.truncate(start);
                return Err(e);
            }
        }
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
    }

    fn random_record(rng: &mut Rng) -> RayRecord {
        let tmax = match rng.next() % 4 {
            0 => f32::INFINITY,
            _ => rng.finite(),
        };
        RayRecord {
            credit: Credit::from_wire(rng.next()),
            origin: rng.finite3(),
            dir: rng.finite3(),
            tmax,
            weight: rng.any_bits3(),
            bsdf_pdf: f32::from_bits(rng.u32()),
            pixel: rng.u32(),
            sample: rng.u32(),
            depth: rng.next() as u16,
            kind: RayKind::ALL[(rng.next() % RayKind::COUNT as u64) as usize],
            flags: (rng.next() as u8) & KNOWN_FLAGS,
        }
    }

    fn bits(r: &RayRecord) -> [u8; RAY_RECORD_BYTES] {
        r.to_bytes()
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
    fn record_is_at_most_64_bytes() {
        const { assert!(RAY_RECORD_BYTES <= 64) };
        let r = random_record(&mut Rng(1));
        let mut out = Vec::new();
        encode_rays(&[r, r, r], &mut out);
        assert_eq!(out.len(), 3 * RAY_RECORD_BYTES);
        assert_eq!(out.len() / 3, 64, "bytes per ray");
    }

    #[test]
    fn round_trip_is_bit_exact() {
        let mut rng = Rng(0x5eed);
        for n in [0usize, 1, 2, 7, 1000] {
            let rays: Vec<RayRecord> = (0..n).map(|_| random_record(&mut rng)).collect();
            let mut bytes = Vec::new();
            encode_rays(&rays, &mut bytes);
            assert_eq!(bytes.len(), n * RAY_RECORD_BYTES);
            let back = decode_rays(&bytes).unwrap();
            assert_eq!(back.len(), n);
            for (a, b) in rays.iter().zip(&back) {
                assert!(same_bits(a, b), "{a:?} != {b:?}");
                assert_eq!(bits(a), bits(b));
            }
            // Re-encoding gives the same bytes.
            let mut again = Vec::new();
            encode_rays(&back, &mut again);
            assert_eq!(bytes, again);
        }
    }

    #[test]
    fn layout_is_as_documented() {
        let r = RayRecord {
            credit: Credit::from_wire(0x0102_0304_0506_0708),
            origin: Vec3::new(1.0, 2.0, 3.0),
            dir: Vec3::new(-1.0, 0.5, 0.25),
            tmax: f32::INFINITY,
            weight: Vec3::new(0.1, 0.2, 0.3),
            bsdf_pdf: 0.75,
            pixel: 0xdead_beef,
            sample: 42,
            depth: 0x0304,
            kind: RayKind::AmbientOcclusion,
            flags: FLAG_TICKETED,
        };
        let b = r.to_bytes();
        assert_eq!(&b[0..8], &[8, 7, 6, 5, 4, 3, 2, 1]);
        assert_eq!(&b[8..12], &1.0f32.to_le_bytes());
        assert_eq!(&b[16..20], &3.0f32.to_le_bytes());
        assert_eq!(&b[20..24], &(-1.0f32).to_le_bytes());
        assert_eq!(&b[32..36], &f32::INFINITY.to_le_bytes());
        assert_eq!(&b[36..40], &0.1f32.to_le_bytes());
        assert_eq!(&b[48..52], &0.75f32.to_le_bytes());
        assert_eq!(&b[52..56], &[0xef, 0xbe, 0xad, 0xde]);
        assert_eq!(&b[56..60], &[42, 0, 0, 0]);
        assert_eq!(&b[60..62], &[4, 3]);
        assert_eq!(b[62], 5);
        assert_eq!(b[63], 1);
        assert!(r.is_ticketed());
    }

    #[test]
    fn every_partial_length_is_an_error() {
        let mut rng = Rng(7);
        let rays: Vec<RayRecord> = (0..4).map(|_| random_record(&mut rng)).collect();
        let mut bytes = Vec::new();
        encode_rays(&rays, &mut bytes);
        for len in 0..=bytes.len() {
            let res = decode_rays(&bytes[..len]);
            if len.is_multiple_of(RAY_RECORD_BYTES) {
                assert_eq!(res.unwrap().len(), len / RAY_RECORD_BYTES);
            } else {
                let err = res.unwrap_err();
                assert_eq!(
                    err,
                    RecordError::Truncated {
                        len,
                        index: len / RAY_RECORD_BYTES
                    }
                );
                assert!(err.to_string().contains("truncated"), "{err}");
            }
        }
        // A misaligned start (one byte dropped at the front) is caught too.
        assert!(decode_rays(&bytes[1..]).is_err());
    }

    #[test]
    fn bad_fields_name_the_record() {
        let mut rng = Rng(9);
        let rays: Vec<RayRecord> = (0..3)
            .map(|_| {
                let mut r = random_record(&mut rng);
                r.tmax = 1.0;
                r
            })
            .collect();
        let mut good = Vec::new();
        encode_rays(&rays, &mut good);
        let base = 2 * RAY_RECORD_BYTES;

        let mut b = good.clone();
        b[base + 62] = RayKind::COUNT as u8;
        assert_eq!(
            decode_rays(&b).unwrap_err(),
            RecordError::UnknownKind { index: 2, kind: 6 }
        );
        b[base + 62] = 255;
        let msg = decode_rays(&b).unwrap_err().to_string();
        assert!(msg.contains("record 2") && msg.contains("255"), "{msg}");

        let mut b = good.clone();
        b[base + 63] = 0x80;
        assert_eq!(
            decode_rays(&b).unwrap_err(),
            RecordError::ReservedFlags {
                index: 2,
                flags: 0x80
            }
        );

        for (offset, field) in [
            (8, "origin"),
            (16, "origin"),
            (20, "direction"),
            (28, "direction"),
        ] {
            for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
                let mut b = good.clone();
                b[base + offset..base + offset + 4].copy_from_slice(&bad.to_le_bytes());
                assert_eq!(
                    decode_rays(&b).unwrap_err(),
                    RecordError::NonFinite { index: 2, field }
                );
            }
        }

        let mut b = good.clone();
        b[base + 32..base + 36].copy_from_slice(&f32::NAN.to_le_bytes());
        assert_eq!(
            decode_rays(&b).unwrap_err(),
            RecordError::NanTmax { index: 2 }
        );

        // decode_rays_into leaves the output untouched on error.
        let mut out = vec![rays[0]];
        assert!(decode_rays_into(&b, &mut out).is_err());
        assert_eq!(out.len(), 1);
    }

    #[test]
    fn garbage_never_panics() {
        let mut rng = Rng(3);
        for len in 0..300 {
            let bytes: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
            let _ = decode_rays(&bytes);
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
        let back = decode_rays(&rec.to_bytes()).unwrap()[0].to_state();
        assert_eq!(back, ray);

        let deep = RayState {
            depth: 70_000,
            ..ray
        };
        assert_eq!(
            RayRecord::from_state(&deep, Credit::from_wire(1)),
            Err(RecordError::DepthTooLarge { depth: 70_000 })
        );
    }
}
