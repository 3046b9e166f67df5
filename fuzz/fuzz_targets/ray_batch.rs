//! The ray-batch decoder: the packed 32-to-64-byte ray record (`dray_core::ray`, format
//! 2) and the `RayBatch` a worker receives on a `RayStream` (protobuf, then the receiver's
//! checks: `count` against the bytes, every record, tickets), plus the records of a cache
//! lookup.
//!
//! The first byte picks the entry, the rest is the input:
//! - 0: raw records, `decode_rays_into` / `decode_rays` (the next byte is the count);
//! - 1: a `RayStreamRequest` message as it arrives on the wire; a batch goes through the
//!   checks of `PeerServer::accept_batch` (`check_count`, `decode_rays_into`,
//!   `peer_client::check_tickets`) and then the receiver's `tickets::with_lineage`;
//! - 2: a `CacheRequest` message; lookups' records are decoded as the cache host does.
//!
//! Oracles besides "no panic": decoding is exact (a decoded batch re-encodes to the same
//! bytes), an error leaves the output untouched and both entry points agree, and a batch
//! that passed the ticket check rebuilds to the same records and tickets through
//! `RayBundle` (the sender's side).

#![no_main]

use dray_core::credit::Credit;
use dray_core::integrator::RayKind;
use dray_core::ray::{RayRecord, check_count, decode_rays, decode_rays_into, encode_rays};
use dray_proto::v1::{CacheRequest, RayBatch, RayStreamRequest, cache_request, ray_stream_request};
use dray_worker::tickets::{RayBundle, check_tickets, with_lineage};
use libfuzzer_sys::fuzz_target;
use prost::Message;

fuzz_target!(init: dray_fuzz::init("ray_batch"), |data: &[u8]| {
    let Some((&selector, rest)) = data.split_first() else {
        return;
    };
    match selector % 3 {
        0 => {
            if let Some((&count, bytes)) = rest.split_first() {
                let _ = records(bytes, usize::from(count));
            }
        }
        1 => {
            if let Ok(req) = RayStreamRequest::decode(rest)
                && let Some(ray_stream_request::Msg::Batch(b)) = req.msg
            {
                batch(&b);
            }
        }
        _ => {
            if let Ok(req) = CacheRequest::decode(rest)
                && let Some(cache_request::Msg::Lookups(l)) = req.msg
                && let Ok(n) = check_count(u64::from(l.count), l.records.len())
            {
                let _ = records(&l.records, n);
            }
        }
    }
});

/// A sentinel already in the output buffer: decoding appends after it and must leave it
/// alone, on success and on error.
fn sentinel() -> RayRecord {
    let v = glam::Vec3::splat(f32::from_bits(0x5a5a_5a5a));
    RayRecord {
        credit: Credit::from_wire(0x5a5a),
        origin: v,
        dir: v,
        tmax: 1.0,
        weight: v,
        bsdf_pdf: 0.5,
        pixel: 0x5a,
        sample: 0x5a,
        depth: 0x5a,
        kind: RayKind::Camera,
        flags: 0,
    }
}

fn records(bytes: &[u8], count: usize) -> Option<Vec<RayRecord>> {
    let s = sentinel();
    let mut out = vec![s];
    let into = decode_rays_into(bytes, count, &mut out);
    let whole = decode_rays(bytes, count);
    assert_eq!(
        out[0].to_bytes(),
        s.to_bytes(),
        "decode_rays_into touched earlier output"
    );
    match into {
        Ok(()) => {
            let rays = out.split_off(1);
            assert_eq!(rays.len(), count);
            let mut again = Vec::new();
            encode_rays(&rays, &mut again);
            assert!(again == bytes, "decode then encode is not the identity");
            let whole = whole.expect("decode_rays fails where decode_rays_into succeeds");
            let mut w = Vec::new();
            encode_rays(&whole, &mut w);
            assert!(w == bytes, "decode_rays and decode_rays_into disagree");
            for r in &rays {
                // The engine's view and back: everything but the flags survives.
                let back = RayRecord::from_state(&r.to_state(), r.credit)
                    .expect("a decoded depth always packs");
                let mut expect = *r;
                expect.flags = 0;
                assert_eq!(back.to_bytes(), expect.to_bytes(), "to_state/from_state");
            }
            Some(rays)
        }
        Err(e) => {
            assert_eq!(
                out.len(),
                1,
                "decode_rays_into kept records of a failed batch"
            );
            assert_eq!(
                whole.as_ref().err(),
                Some(&e),
                "decode_rays and decode_rays_into disagree"
            );
            let _ = e.to_string();
            None
        }
    }
}

/// What `PeerServer::accept_batch` checks before queueing a batch, then what the
/// receiver does with the tickets.
fn batch(b: &RayBatch) {
    let Ok(n) = check_count(u64::from(b.count), b.records.len()) else {
        return;
    };
    let Some(rays) = records(&b.records, n) else {
        return;
    };
    if check_tickets(&rays, &b.tickets).is_err() {
        return;
    }
    // Accepted: the receiver walks the rays with their lineages; the sender's bundle of
    // the same rays and lineages is the same batch.
    let mut bundle = RayBundle::default();
    for (ray, lineage) in with_lineage(&rays, &b.tickets) {
        bundle.push(*ray, &lineage);
    }
    let mut bytes = Vec::new();
    encode_rays(&bundle.rays, &mut bytes);
    assert!(
        bytes == b.records,
        "an accepted batch does not rebuild to its records"
    );
    assert_eq!(
        bundle.tickets, b.tickets,
        "an accepted batch does not rebuild to its tickets"
    );
    check_tickets(&bundle.rays, &bundle.tickets).expect("a rebuilt batch passes the check");
}
