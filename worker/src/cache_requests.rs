//! How the worker writes what it sends a cache host as `cache.proto` requests: one
//! builder per message, so the link's task ([`crate::cache_link`]) only chunks,
//! numbers, counts and sends. The lookups' ray records and option bits are also what
//! the cache host in this process is handed directly.

use dray_cache::Entry;
use dray_cache::entry_record::{ENTRY_RECORD_BYTES, encode_entry};
use dray_cache::wire::{OPTION_ANSWER, OPTION_PHM, OPTION_ROOM, OPTION_TICKET};
use dray_core::ray::{FLAG_COARSE, RayRecord, encode_rays};
use dray_proto::v1::{
    CacheLookups, CacheRequest, PhmMerge, PhmOutcomes, TicketReturn, TicketReturns, WallEntries,
    cache_request,
};

use crate::jobs::Job;
use crate::tickets::MAX_TICKETS;
use crate::tracer::Lookup;

/// The ray as its wall's actor sees it: the actor reads the coarse flag from the
/// record (a coarse ray's ticket stores even when the main pass does not fill).
pub(crate) fn lookup_record(l: &Lookup) -> RayRecord {
    let mut r = l.ray;
    if l.lineage.coarse {
        r.flags |= FLAG_COARSE;
    }
    r
}

/// A lookup's option bits (cache.proto `CacheLookups.options`).
pub(crate) fn lookup_options(job: &Job, l: &Lookup) -> u32 {
    let mut o = 0;
    if l.cache {
        // The coarse pass is exact: its rays fill the caches, never ask.
        if !l.lineage.coarse {
            o |= OPTION_ANSWER;
        }
        if job.tracer.opens_ticket(&l.lineage) {
            o |= OPTION_TICKET;
        }
    }
    if l.phm {
        o |= OPTION_PHM;
        // A map that shades may ticket the ray to learn its radiance (the ray cache's
        // ticket at this wall, if any, is the same one).
        if l.lineage.ticket_count() < MAX_TICKETS {
            o |= OPTION_ROOM;
        }
    }
    o
}

/// Payload of a lookups message for `cache_bytes`: its ray records (32 to 64 bytes each)
/// and 8 bytes a ray for its wall and options.
pub(crate) fn lookup_payload(request: &CacheRequest, rays: usize) -> u64 {
    let records = match &request.msg {
        Some(cache_request::Msg::Lookups(l)) => l.records.len(),
        _ => 0,
    };
    (records + 8 * rays) as u64
}

/// Rays at walls, to be answered ray for ray.
pub(crate) fn lookups_request(job: &Job, sequence: u64, lookups: &[Lookup]) -> CacheRequest {
    let rays: Vec<_> = lookups.iter().map(lookup_record).collect();
    let mut records = Vec::new();
    encode_rays(&rays, &mut records);
    CacheRequest {
        msg: Some(cache_request::Msg::Lookups(CacheLookups {
            job_id: job.key.id.to_string(),
            attempt: job.key.attempt,
            sequence,
            count: lookups.len() as u32,
            records,
            walls: lookups.iter().map(|l| l.wall).collect(),
            options: lookups.iter().map(|l| lookup_options(job, l)).collect(),
        })),
    }
}

/// Ticket returns, to be acknowledged.
pub(crate) fn returns_request(
    job: &Job,
    sequence: u64,
    returns: Vec<TicketReturn>,
) -> CacheRequest {
    CacheRequest {
        msg: Some(cache_request::Msg::Returns(TicketReturns {
            job_id: job.key.id.to_string(),
            attempt: job.key.attempt,
            sequence,
            returns,
        })),
    }
}

/// Hit-map probe outcomes (wall, cell, hit), to be acknowledged.
pub(crate) fn outcomes_request(
    job: &Job,
    sequence: u64,
    outcomes: &[(u32, u32, bool)],
) -> CacheRequest {
    CacheRequest {
        msg: Some(cache_request::Msg::Outcomes(PhmOutcomes {
            job_id: job.key.id.to_string(),
            attempt: job.key.attempt,
            sequence,
            walls: outcomes.iter().map(|o| o.0).collect(),
            cells: outcomes.iter().map(|o| o.1).collect(),
            hits: outcomes.iter().map(|o| u8::from(o.2)).collect(),
        })),
    }
}

/// Outcomes gathered per cell for another worker's copies of the maps (wall, cell,
/// hits, misses), to be acknowledged.
pub(crate) fn merge_request(
    job: &Job,
    sequence: u64,
    cells: &crate::map_merge::Merge,
) -> CacheRequest {
    CacheRequest {
        msg: Some(cache_request::Msg::Merge(PhmMerge {
            job_id: job.key.id.to_string(),
            attempt: job.key.attempt,
            sequence,
            walls: cells.iter().map(|c| c.0).collect(),
            cells: cells.iter().map(|c| c.1).collect(),
            hits: cells.iter().map(|c| c.2).collect(),
            misses: cells.iter().map(|c| c.3).collect(),
        })),
    }
}

/// Entries another replica of their walls stored (wall, entry), to be acknowledged.
pub(crate) fn entries_request(job: &Job, sequence: u64, entries: &[(u32, Entry)]) -> CacheRequest {
    let mut records = Vec::with_capacity(entries.len() * ENTRY_RECORD_BYTES);
    for (_, e) in entries {
        encode_entry(e, &mut records);
    }
    CacheRequest {
        msg: Some(cache_request::Msg::Entries(WallEntries {
            job_id: job.key.id.to_string(),
            attempt: job.key.attempt,
            sequence,
            walls: entries.iter().map(|(w, _)| *w).collect(),
            entries: records,
        })),
    }
}
