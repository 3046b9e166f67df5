//! Ray-cache tickets on the worker's side (docs/caches.md "Walls").
//!
//! A ray that missed a wall's cache travels on with a *ticket* from that wall's actor.
//! Its children inherit its tickets, so every contribution and every unit of credit the
//! ray's descendants hand back can also be returned to each ticket: the actor then knows
//! what the ray saw beyond the wall, and when (its credit whole) it has seen all of it.
//! A ray keeps at most [`MAX_TICKETS`] tickets (the outermost walls it missed); deeper
//! walls still answer it but no longer ticket it.
//!
//! This file holds the three shapes tickets take here: a ray's [`TicketSet`], a batch's
//! sparse table ([`RayBundle`], the wire's `RayBatch.tickets`), and the per-ticket sums
//! waiting to be returned ([`TicketLedger`]).

use std::collections::HashMap;
use std::fmt;
use std::ops::Deref;

use dray_core::credit::Credit;
use dray_core::film::add_sums;
use dray_core::ray::{FLAG_COARSE, FLAG_PROBE, FLAG_TICKETED, RayRecord};
use dray_proto::v1::{RayTicket, TicketReturn};

/// The most tickets a ray carries.
pub const MAX_TICKETS: usize = 8;

/// Tickets one ray carries, outermost first, at most [`MAX_TICKETS`], held inline.
///
/// Why inline: a ray's set is copied to each of its children (72 bytes), which costs less
/// than what a shared `Arc<[u64]>` did: an allocation for every ray that gained a ticket
/// or arrived with one, and an atomic count for every child
/// (docs/history/2026-11-26-lean-tickets.md). It reads as a slice of tickets (`iter`, `len`,
/// `to_vec`, ...).
#[derive(Clone, PartialEq, Eq, Hash)]
pub struct TicketSet {
    tickets: [u64; MAX_TICKETS],
    len: u8,
}

impl TicketSet {
    /// The set of one ticket.
    pub fn one(ticket: u64) -> TicketSet {
        let mut tickets = [0; MAX_TICKETS];
        tickets[0] = ticket;
        TicketSet { tickets, len: 1 }
    }

    /// The set with `ticket` appended; `None` when it already holds [`MAX_TICKETS`].
    pub fn with(&self, ticket: u64) -> Option<TicketSet> {
        let mut out = self.clone();
        *out.tickets.get_mut(usize::from(self.len))? = ticket;
        out.len += 1;
        Some(out)
    }

    /// The tickets of `tickets` up to the first [`MAX_TICKETS`] (a receiver has checked
    /// that a ray has no more), and `None` for none.
    pub fn from_tickets(tickets: impl IntoIterator<Item = u64>) -> Option<TicketSet> {
        let mut set = TicketSet {
            tickets: [0; MAX_TICKETS],
            len: 0,
        };
        for (slot, t) in set.tickets.iter_mut().zip(tickets) {
            *slot = t;
            set.len += 1;
        }
        (set.len > 0).then_some(set)
    }
}

impl Deref for TicketSet {
    type Target = [u64];

    fn deref(&self) -> &[u64] {
        &self.tickets[..usize::from(self.len)]
    }
}

impl fmt::Debug for TicketSet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_list().entries(self.iter()).finish()
    }
}

impl From<Vec<u64>> for TicketSet {
    /// The first [`MAX_TICKETS`] of `v` (an empty set for an empty `v`).
    fn from(v: Vec<u64>) -> TicketSet {
        TicketSet::from_tickets(v).unwrap_or(TicketSet {
            tickets: [0; MAX_TICKETS],
            len: 0,
        })
    }
}

/// A ray's tickets with one more appended (a ray that missed another wall's cache). A set
/// that is already full stays as it is: callers ask for a ticket only below
/// [`MAX_TICKETS`] (and a ray never arrives with more), so this does not happen.
pub fn with_ticket(set: Option<&TicketSet>, ticket: u64) -> TicketSet {
    match set {
        None => TicketSet::one(ticket),
        Some(s) => s.with(ticket).unwrap_or_else(|| {
            debug_assert!(false, "a ninth ticket for a ray");
            s.clone()
        }),
    }
}

/// What a ray inherits from its ancestors: the tickets it owes what it hands back to,
/// and whether it belongs to the coarse pass (whose rays fill caches and add nothing to
/// the image).
///
/// `probe` is the one part not inherited: a hit map asked for this ray's outcome in the
/// domain it enters next, and only there.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Lineage {
    pub tickets: Option<TicketSet>,
    pub coarse: bool,
    pub probe: bool,
}

impl Lineage {
    /// The lineage of a received ray: its coarse and probe flags and its tickets.
    pub fn of(ray: &RayRecord, tickets: Option<TicketSet>) -> Lineage {
        Lineage {
            tickets,
            coarse: ray.flags & FLAG_COARSE != 0,
            probe: ray.flags & FLAG_PROBE != 0,
        }
    }

    /// The same lineage with one more ticket (the ray missed another wall's cache).
    pub fn with_ticket(&self, ticket: u64) -> Lineage {
        Lineage {
            tickets: Some(with_ticket(self.tickets.as_ref(), ticket)),
            coarse: self.coarse,
            probe: self.probe,
        }
    }

    /// What a child inherits (everything but the probe).
    pub fn inherited(&self) -> Lineage {
        Lineage {
            tickets: self.tickets.clone(),
            coarse: self.coarse,
            probe: false,
        }
    }

    /// Tickets carried.
    pub fn ticket_count(&self) -> usize {
        self.tickets.as_ref().map_or(0, |t| t.len())
    }
}

/// Rays bound for one place, with their tickets in the wire's sparse form: one
/// [`RayTicket`] per ticket, by record index, in increasing record order.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct RayBundle {
    pub rays: Vec<RayRecord>,
    pub tickets: Vec<RayTicket>,
}

impl RayBundle {
    /// Append a ray with its lineage; its TICKETED, COARSE and PROBE flags are set to
    /// match.
    pub fn push(&mut self, mut ray: RayRecord, lineage: &Lineage) {
        let index = self.rays.len() as u32;
        for (flag, on) in [(FLAG_COARSE, lineage.coarse), (FLAG_PROBE, lineage.probe)] {
            if on {
                ray.flags |= flag;
            } else {
                ray.flags &= !flag;
            }
        }
        match &lineage.tickets {
            Some(set) if !set.is_empty() => {
                ray.flags |= FLAG_TICKETED;
                self.tickets.extend(set.iter().map(|&ticket| RayTicket {
                    record: index,
                    ticket,
                }));
            }
            _ => ray.flags &= !FLAG_TICKETED,
        }
        self.rays.push(ray);
    }

    pub fn len(&self) -> usize {
        self.rays.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rays.is_empty()
    }

    /// Every ray with its lineage.
    pub fn iter(&self) -> impl Iterator<Item = (&RayRecord, Lineage)> {
        with_lineage(&self.rays, &self.tickets)
    }
}

/// Walk `rays` with their lineages, tickets from a sparse table sorted by record (as
/// checked on arrival); tickets naming no ray, and beyond a ray's first [`MAX_TICKETS`]
/// (which the arrival check refuses), are ignored.
pub fn with_lineage<'a>(
    rays: &'a [RayRecord],
    tickets: &'a [RayTicket],
) -> impl Iterator<Item = (&'a RayRecord, Lineage)> + 'a {
    let mut at = 0usize;
    rays.iter().enumerate().map(move |(i, r)| {
        while at < tickets.len() && (tickets[at].record as usize) < i {
            at += 1;
        }
        let start = at;
        while at < tickets.len() && tickets[at].record as usize == i {
            at += 1;
        }
        let set = TicketSet::from_tickets(tickets[start..at].iter().map(|t| t.ticket));
        (r, Lineage::of(r, set))
    })
}

/// What one ticket has been handed since its last return.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TicketSums {
    pub sum: [i64; 3],
    pub credit: Credit,
    pub tainted: bool,
}

/// The ledger hashes tickets with foldhash: ticket ids are issued by the cache actors, not
/// chosen by a peer, and SipHash cost more than the sums it indexes.
type FastState = foldhash::fast::FixedState;

/// Contributions and credit owed to tickets, by ticket.
#[derive(Debug, Default)]
pub struct TicketLedger {
    by_ticket: HashMap<u64, TicketSums, FastState>,
}

impl TicketLedger {
    pub fn is_empty(&self) -> bool {
        self.by_ticket.is_empty()
    }

    /// A contribution (film fixed point) made under `tickets`; `cached` when it came
    /// from a cache's answer (the tickets must then not store their radiance).
    pub fn contribute(&mut self, tickets: &TicketSet, value: [i64; 3], cached: bool) {
        for &t in tickets.iter() {
            let e = self.by_ticket.entry(t).or_default();
            add_sums(&mut e.sum, value);
            e.tainted |= cached;
        }
    }

    /// Credit handed back under `tickets`.
    pub fn credit(&mut self, tickets: &TicketSet, credit: Credit, cached: bool) {
        if credit.is_zero() && !cached {
            return;
        }
        for &t in tickets.iter() {
            let e = self.by_ticket.entry(t).or_default();
            e.credit = e.credit.saturating_add(credit);
            e.tainted |= cached;
        }
    }

    /// Add another ledger's entries.
    pub fn merge(&mut self, other: TicketLedger) {
        for (t, o) in other.by_ticket {
            let e = self.by_ticket.entry(t).or_default();
            add_sums(&mut e.sum, o.sum);
            e.credit = e.credit.saturating_add(o.credit);
            e.tainted |= o.tainted;
        }
    }

    /// Everything owed, as wire returns, emptying the ledger.
    pub fn drain(&mut self) -> Vec<TicketReturn> {
        let mut out: Vec<TicketReturn> = self
            .by_ticket
            .drain()
            .map(|(ticket, s)| TicketReturn {
                ticket,
                r: s.sum[0],
                g: s.sum[1],
                b: s.sum[2],
                credit: s.credit.to_wire(),
                tainted: s.tainted,
            })
            .collect();
        out.sort_unstable_by_key(|r| r.ticket);
        out
    }
}

/// Tickets must name, in non-decreasing record order, exactly the records flagged
/// TICKETED, each at least once and at most [`MAX_TICKETS`] times: what a receiver
/// checks on arrival, so a sender checks it before sending.
pub fn check_tickets(rays: &[RayRecord], tickets: &[RayTicket]) -> Result<(), String> {
    let mut at = 0usize;
    for (i, r) in rays.iter().enumerate() {
        let start = at;
        while at < tickets.len() && usize::try_from(tickets[at].record).ok() == Some(i) {
            at += 1;
        }
        let n = at - start;
        if r.flags & FLAG_TICKETED != 0 {
            if n == 0 {
                return Err(format!("record {i} is ticketed but has no ticket"));
            }
            if n > MAX_TICKETS {
                return Err(format!(
                    "record {i} has {n} tickets, more than {MAX_TICKETS}"
                ));
            }
        } else if n > 0 {
            return Err(format!("ticket for record {i}, which is not ticketed"));
        }
        if let Some(t) = tickets.get(at)
            && usize::try_from(t.record).ok().is_none_or(|rec| rec <= i)
        {
            return Err(format!(
                "ticket for record {} out of order after record {i}",
                t.record
            ));
        }
    }
    match tickets.get(at) {
        Some(t) => Err(format!(
            "ticket for record {}, beyond the batch's {} records",
            t.record,
            rays.len()
        )),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_cache::ticket_id::ticket_id;
    use dray_core::integrator::RayKind;
    use glam::Vec3;

    fn ray(pixel: u32) -> RayRecord {
        RayRecord {
            credit: Credit::from_wire(10),
            origin: Vec3::ZERO,
            dir: Vec3::X,
            tmax: f32::INFINITY,
            weight: Vec3::ONE,
            bsdf_pdf: 0.0,
            pixel,
            sample: 0,
            depth: 0,
            kind: RayKind::Camera,
            flags: 0,
        }
    }

    #[test]
    fn bundles_keep_each_rays_tickets() {
        let mut b = RayBundle::default();
        let two: TicketSet = vec![ticket_id(0, 7, 1), ticket_id(0, 9, 4)].into();
        let coarse = Lineage {
            tickets: None,
            coarse: true,
            probe: false,
        };
        b.push(ray(0), &Lineage::default());
        b.push(
            ray(1),
            &Lineage {
                tickets: Some(two.clone()),
                coarse: false,
                probe: true,
            },
        );
        b.push(ray(2), &coarse.with_ticket(5));
        assert_eq!(b.tickets.len(), 3);
        let sets: Vec<Option<Vec<u64>>> = b
            .iter()
            .map(|(_, l)| l.tickets.map(|s| s.to_vec()))
            .collect();
        assert_eq!(sets, [None, Some(two.to_vec()), Some(vec![5])]);
        let flags: Vec<u8> = b.rays.iter().map(|r| r.flags).collect();
        assert_eq!(
            flags,
            [0, FLAG_TICKETED | FLAG_PROBE, FLAG_TICKETED | FLAG_COARSE]
        );
        assert!(b.iter().last().is_some_and(|(_, l)| l.coarse));
    }

    #[test]
    fn the_ledger_sums_per_ticket() {
        let mut l = TicketLedger::default();
        let a: TicketSet = vec![1, 2].into();
        let b: TicketSet = vec![2].into();
        l.contribute(&a, [1, 2, 3], false);
        l.credit(&a, Credit::from_wire(5), false);
        let mut m = TicketLedger::default();
        m.contribute(&b, [10, 10, 10], true);
        m.credit(&b, Credit::from_wire(1), true);
        l.merge(m);
        let r = l.drain();
        assert!(l.is_empty());
        assert_eq!(r.len(), 2);
        assert_eq!(
            (r[0].ticket, r[0].r, r[0].credit, r[0].tainted),
            (1, 1, 5, false)
        );
        assert_eq!(
            (r[1].ticket, r[1].r, r[1].credit, r[1].tainted),
            (2, 11, 6, true)
        );
    }
}
