//! One wall's open tickets: a ray that missed the cache leaves with a ticket, its
//! descendants hand contributions and credit back to it, and when the credit is whole
//! the radiance along the ray is known: `sum / weight at the wall`
//! (docs/architecture.md "Credit"). The same tickets teach a shading hit map
//! (`phm.shade`) what its probes returned: a ticket may serve the wall's ray cache, its
//! hit map's cell, or both, and closes once for both.
//!
//! Credit is the only completion signal that survives reordering and retries: returns
//! can arrive in any order, from any worker, split any way, and the ticket closes
//! exactly when their credit adds up to the ray's. Returns that do not fit (more credit
//! than the ray had, a ticket that is not open) are counted and dropped; they mean a
//! bug or a duplicate somewhere else, and must not take the host down.

use std::collections::{HashMap, VecDeque};

use dray_core::credit::Credit;
use dray_core::film::FIXED_SCALE;
use dray_proto::v1::TicketReturn;
use glam::Vec3;

use crate::store::{Entry, EntryKey};
use crate::ticket_id::ticket_id;

/// The map of old open tickets hashes a slot with foldhash: slots are issued by the book
/// itself (no one can choose them to collide), and SipHash costs more than a return.
type FastState = foldhash::fast::FixedState;

/// Tickets a wall keeps open by default; past it, misses get no ticket (and the worker
/// traces them without caching), which bounds the memory a flood of lookups can take.
pub const DEFAULT_MAX_OPEN_TICKETS: usize = 1 << 22;

/// Everything a ticket remembers about the ray that opened it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TicketRay {
    pub key: EntryKey,
    /// Crossing point, wall coordinates.
    pub point: [f32; 2],
    /// Unit direction.
    pub dir: Vec3,
    /// Throughput at the wall: the contributions coming back are `weight * radiance`.
    pub weight: Vec3,
    /// The ray's credit: the ticket closes when this much has come back.
    pub credit: Credit,
    /// The ray belongs to the coarse pass, whose tickets store even when the job's main
    /// pass does not fill the caches.
    pub coarse: bool,
    /// The ray cache asked for the ticket: its radiance is an entry for the store.
    pub cache: bool,
    /// The hit map's cell the ray entered by, when the map asked for the ticket
    /// (`phm.shade`): its radiance is added to the cell's averaged shading.
    pub cell: Option<u32>,
}

#[derive(Clone, Copy, Debug)]
struct Ticket {
    ray: TicketRay,
    returned: Credit,
    /// Fixed-point sums (24 fractional bits). i128 so no sequence of i64 returns can
    /// overflow; saturating anyway, so even that cannot panic.
    sums: [i128; 3],
    tainted: bool,
}

/// One return, as applied to a ticket.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Return {
    /// Contribution sums, fixed point.
    pub rgb: [i64; 3],
    pub credit: Credit,
    pub tainted: bool,
}

impl From<&TicketReturn> for Return {
    /// A return as `TicketReturns` carries it (its ticket aside).
    fn from(t: &TicketReturn) -> Return {
        Return {
            rgb: [t.r, t.g, t.b],
            credit: Credit::from_wire(t.credit),
            tainted: t.tainted,
        }
    }
}

/// What applying a return did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Applied {
    /// Added; the ticket waits for more credit.
    Pending,
    /// The ticket closed. `entry` is the entry to store, `None` when the ray cache did
    /// not ask for the ticket or the radiance must not or cannot be stored; `shading`
    /// the hit map's cell and the radiance to add to its averaged shading, under the
    /// same rule.
    Closed {
        entry: Option<Entry>,
        shading: Option<(u32, [f32; 3])>,
    },
    /// The ticket is not open (never issued here, or already closed).
    Unknown,
    /// The return carried more credit than the ticket still waited for; ignored, and
    /// the ticket stays as it was.
    OverCredit,
}

/// Why a miss got no ticket.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum OpenError {
    #[error("the wall has too many open tickets")]
    TooMany,
    #[error("the wall has issued every ticket id it can")]
    Exhausted,
    #[error("a ray without credit could never close its ticket")]
    NoCredit,
}

/// Slots a book keeps in its window (144 bytes a slot: 9 MiB) before it moves the
/// oldest tickets still open out to its map.
const WINDOW: usize = 1 << 16;

/// The open tickets of one wall.
///
/// Slots are issued in order, and tickets mostly close in about that order (a worker
/// returns a tile's tickets together, sorted), so tickets live in a window indexed by
/// `slot - base`: a return finds its ticket without hashing, and a run of returns reads
/// neighbouring memory. Tickets that stay open while [`WINDOW`] newer ones open (a ray
/// whose descendants take long) move to a map, so one straggler cannot make the window
/// grow without bound.
pub struct TicketBook {
    wall: u32,
    /// The next slot to issue; slot 0 is never issued, so a zero ticket is never valid.
    next_slot: u32,
    /// The tickets of slots `base..base + recent.len()`; `None` once closed (or moved).
    recent: VecDeque<Option<Ticket>>,
    base: u32,
    /// Open tickets of slots below `base`.
    old: HashMap<u32, Ticket, FastState>,
    open: usize,
    max_open: usize,
}

impl TicketBook {
    pub fn new(wall: u32, max_open: usize) -> TicketBook {
        TicketBook {
            wall,
            next_slot: 1,
            recent: VecDeque::new(),
            base: 1,
            old: HashMap::default(),
            open: 0,
            max_open,
        }
    }

    /// Tickets open now.
    pub fn open_count(&self) -> usize {
        self.open
    }

    /// Open a ticket for `ray`; returns its id ([`ticket_id`], replica 0: the host sets
    /// the replica that issued it).
    pub fn open(&mut self, ray: TicketRay) -> Result<u64, OpenError> {
        if ray.credit.is_zero() {
            return Err(OpenError::NoCredit);
        }
        if self.open >= self.max_open {
            return Err(OpenError::TooMany);
        }
        let slot = self.next_slot;
        if slot == 0 {
            return Err(OpenError::Exhausted);
        }
        // Wraps to 0 after u32::MAX, which then refuses further tickets.
        self.next_slot = slot.wrapping_add(1);
        if u64::from(self.base) + self.recent.len() as u64 != u64::from(slot) {
            // Not the window's next slot (only when `next_slot` was set by hand): start a
            // new window there.
            self.retire(self.recent.len());
            self.base = slot;
        }
        if self.recent.len() >= WINDOW {
            self.retire(self.recent.len() + 1 - WINDOW);
        }
        self.recent.push_back(Some(Ticket {
            ray,
            returned: Credit::ZERO,
            sums: [0; 3],
            tainted: false,
        }));
        self.open += 1;
        Ok(ticket_id(0, self.wall, slot))
    }

    /// Move the window's first `n` slots out of it: their open tickets to the map.
    fn retire(&mut self, n: usize) {
        for _ in 0..n {
            let Some(front) = self.recent.pop_front() else {
                return;
            };
            if let Some(t) = front {
                self.old.insert(self.base, t);
            }
            self.base = self.base.wrapping_add(1);
        }
    }

    /// The open ticket in `slot`, if any.
    fn ticket(&mut self, slot: u32) -> Option<&mut Ticket> {
        match slot.checked_sub(self.base) {
            Some(i) => self.recent.get_mut(i as usize)?.as_mut(),
            None => self.old.get_mut(&slot),
        }
    }

    /// Close the ticket in `slot` (open, as [`TicketBook::ticket`] found it).
    fn close(&mut self, slot: u32) {
        self.open = self.open.saturating_sub(1);
        match slot.checked_sub(self.base) {
            Some(i) => {
                if let Some(t) = self.recent.get_mut(i as usize) {
                    *t = None;
                }
                // Closed slots at the front leave the window.
                while matches!(self.recent.front(), Some(None)) {
                    self.recent.pop_front();
                    self.base = self.base.wrapping_add(1);
                }
            }
            None => {
                self.old.remove(&slot);
            }
        }
    }

    /// Apply one return to the ticket in `slot`. `fill` says whether a clean close of a
    /// main-pass ticket stores its radiance (coarse-pass tickets always do).
    pub fn apply(&mut self, slot: u32, ret: Return, fill: bool) -> Applied {
        let Some(t) = self.ticket(slot) else {
            return Applied::Unknown;
        };
        let Some(returned) = t.returned.checked_add(ret.credit) else {
            return Applied::OverCredit;
        };
        if returned > t.ray.credit {
            return Applied::OverCredit;
        }
        t.returned = returned;
        for (s, v) in t.sums.iter_mut().zip(ret.rgb) {
            *s = s.saturating_add(i128::from(v));
        }
        t.tainted |= ret.tainted;
        if returned < t.ray.credit {
            return Applied::Pending;
        }
        let store = t.ray.cache && (fill || t.ray.coarse);
        let wanted = store || t.ray.cell.is_some();
        let radiance = if wanted { radiance(t) } else { None };
        let entry = radiance.filter(|_| store).map(|radiance| Entry {
            key: t.ray.key,
            point: t.ray.point,
            dir: t.ray.dir,
            radiance,
        });
        let shading = t.ray.cell.zip(radiance);
        self.close(slot);
        Applied::Closed { entry, shading }
    }
}

/// The radiance along a cleanly closed ticket's ray: (sum / 2^24) / weight per channel.
/// `None` when a cache or a hit map answered some descendant (tainted: its radiance
/// rests on an approximation and must not be learned again), when a weight channel is
/// not a finite positive number (the radiance cannot be recovered from the sum), or
/// when the result is not a finite non-negative radiance.
fn radiance(t: &Ticket) -> Option<[f32; 3]> {
    if t.tainted {
        return None;
    }
    let w = t.ray.weight.to_array();
    if !w.iter().all(|c| c.is_finite() && *c > 0.0) {
        return None;
    }
    let mut radiance = [0f32; 3];
    for ((out, sum), weight) in radiance.iter_mut().zip(t.sums).zip(w) {
        let r = ((sum as f64 / FIXED_SCALE) / f64::from(weight)) as f32;
        if !(r.is_finite() && r >= 0.0) {
            return None;
        }
        *out = r;
    }
    Some(radiance)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ticket_id::{ticket_replica, ticket_slot, ticket_wall};

    fn coarse_ray(credit: u64) -> TicketRay {
        TicketRay {
            coarse: true,
            ..ray(credit, Vec3::ONE)
        }
    }

    fn ray(credit: u64, weight: Vec3) -> TicketRay {
        TicketRay {
            key: EntryKey {
                pixel: 3,
                sample: 1,
                depth: 0,
                kind: 0,
                origin: [0; 3],
                dir: [0; 3],
            },
            point: [0.25, 0.5],
            dir: Vec3::X,
            weight,
            credit: Credit::from_wire(credit),
            coarse: false,
            cache: true,
            cell: None,
        }
    }

    fn ret(rgb: [i64; 3], credit: u64) -> Return {
        Return {
            rgb,
            credit: Credit::from_wire(credit),
            tainted: false,
        }
    }

    #[test]
    fn closes_exactly_once_when_credit_is_whole() {
        let mut book = TicketBook::new(7, 16);
        let id = book.open(ray(10, Vec3::new(0.5, 0.25, 1.0))).unwrap();
        assert_eq!((ticket_wall(id), ticket_replica(id)), (7, 0));
        let slot = ticket_slot(id);
        assert_eq!(slot, 1);
        let one = 1i64 << 24;
        assert_eq!(
            book.apply(slot, ret([one, one, 0], 3), true),
            Applied::Pending
        );
        assert_eq!(
            book.apply(slot, ret([0, 0, one], 0), true),
            Applied::Pending
        );
        assert_eq!(
            book.apply(slot, ret([one, 0, 0], 6), true),
            Applied::Pending
        );
        let Applied::Closed { entry: Some(e), .. } = book.apply(slot, ret([0, one, one], 1), true)
        else {
            panic!("should close and store");
        };
        // Sums are (2, 2, 2); divided by the weight.
        assert_eq!(e.radiance, [4.0, 8.0, 2.0]);
        assert_eq!(e.point, [0.25, 0.5]);
        assert_eq!(book.open_count(), 0);
        // Closed: further returns are unknown, never a second close.
        assert_eq!(book.apply(slot, ret([1, 1, 1], 1), true), Applied::Unknown);
        assert_eq!(book.apply(slot, ret([1, 1, 1], 0), true), Applied::Unknown);
    }

    #[test]
    fn tainted_and_zero_weight_close_without_storing() {
        let mut book = TicketBook::new(0, 16);
        let a = ticket_slot(book.open(ray(2, Vec3::ONE)).unwrap());
        let b = ticket_slot(book.open(ray(2, Vec3::new(1.0, 0.0, 1.0))).unwrap());
        let c = ticket_slot(book.open(ray(2, Vec3::new(1.0, f32::NAN, 1.0))).unwrap());
        let d = ticket_slot(book.open(ray(1, Vec3::ONE)).unwrap());
        assert_eq!(
            book.apply(
                a,
                Return {
                    tainted: true,
                    ..ret([5, 5, 5], 1)
                },
                true
            ),
            Applied::Pending
        );
        assert_eq!(
            book.apply(a, ret([5, 5, 5], 1), true),
            Applied::Closed {
                entry: None,
                shading: None
            }
        );
        assert_eq!(
            book.apply(b, ret([5, 5, 5], 2), true),
            Applied::Closed {
                entry: None,
                shading: None
            }
        );
        assert_eq!(
            book.apply(c, ret([5, 5, 5], 2), true),
            Applied::Closed {
                entry: None,
                shading: None
            }
        );
        // The job does not fill: a clean close still stores nothing, unless the ray was
        // of the coarse pass.
        assert_eq!(
            book.apply(d, ret([5, 5, 5], 1), false),
            Applied::Closed {
                entry: None,
                shading: None
            }
        );
        let e = ticket_slot(book.open(coarse_ray(1)).unwrap());
        assert!(matches!(
            book.apply(e, ret([5, 5, 5], 1), false),
            Applied::Closed { entry: Some(_), .. }
        ));
    }

    /// A ticket a hit map asked for (`phm.shade`) hands its radiance to the map's cell
    /// when it closes cleanly, whether or not the ray cache asked for it too and
    /// whether or not the job fills the caches; a tainted one (a cache or a map answered
    /// a descendant) hands over nothing, and stores nothing either.
    #[test]
    fn map_tickets_teach_their_cell_unless_tainted() {
        let mut book = TicketBook::new(2, 16);
        let map_only = TicketRay {
            cache: false,
            cell: Some(17),
            ..ray(2, Vec3::new(0.5, 1.0, 2.0))
        };
        let one = 1i64 << 24;
        // Clean, map only: the cell learns, no entry is stored even though the job fills.
        let a = ticket_slot(book.open(map_only).unwrap());
        assert_eq!(book.apply(a, ret([one, one, 0], 1), true), Applied::Pending);
        assert_eq!(
            book.apply(a, ret([0, one, one], 1), true),
            Applied::Closed {
                entry: None,
                shading: Some((17, [2.0, 2.0, 0.5]))
            }
        );
        // Both asked: one close serves both; the entry follows `fill`, the cell does not.
        let both = TicketRay {
            cache: true,
            ..map_only
        };
        let b = ticket_slot(book.open(both).unwrap());
        let Applied::Closed {
            entry: Some(e),
            shading: Some((17, rgb)),
        } = book.apply(b, ret([one, one, one], 2), true)
        else {
            panic!("should store and shade");
        };
        assert_eq!(e.radiance, rgb);
        let c = ticket_slot(book.open(both).unwrap());
        assert_eq!(
            book.apply(c, ret([one, one, one], 2), false),
            Applied::Closed {
                entry: None,
                shading: Some((17, [2.0, 1.0, 0.5]))
            }
        );
        // Tainted by an answered descendant (a zero-credit return, as a map's skip
        // sends, or the credit of a shaded or cached answer): nothing for anyone.
        for both in [false, true] {
            let t = ticket_slot(
                book.open(TicketRay {
                    cache: both,
                    ..map_only
                })
                .unwrap(),
            );
            let taint = Return {
                tainted: true,
                ..ret([one, one, one], 0)
            };
            assert_eq!(book.apply(t, taint, true), Applied::Pending);
            assert_eq!(
                book.apply(t, ret([one, one, one], 2), true),
                Applied::Closed {
                    entry: None,
                    shading: None
                }
            );
        }
        // A weight that cannot be divided by: nothing either.
        let d = ticket_slot(
            book.open(TicketRay {
                weight: Vec3::new(1.0, 0.0, 1.0),
                ..map_only
            })
            .unwrap(),
        );
        assert_eq!(
            book.apply(d, ret([one, 0, one], 2), true),
            Applied::Closed {
                entry: None,
                shading: None
            }
        );
        assert_eq!(book.open_count(), 0);
    }

    #[test]
    fn over_credit_is_refused_and_the_ticket_survives() {
        let mut book = TicketBook::new(0, 16);
        let s = ticket_slot(book.open(ray(4, Vec3::ONE)).unwrap());
        assert_eq!(book.apply(s, ret([1, 1, 1], 3), true), Applied::Pending);
        assert_eq!(book.apply(s, ret([9, 9, 9], 2), true), Applied::OverCredit);
        assert_eq!(
            book.apply(s, ret([9, 9, 9], u64::MAX), true),
            Applied::OverCredit
        );
        let Applied::Closed { entry: Some(e), .. } = book.apply(s, ret([1, 1, 1], 1), true) else {
            panic!("should close");
        };
        assert_eq!(e.radiance, [2.0 / FIXED_SCALE as f32; 3]);
    }

    #[test]
    fn extreme_sums_do_not_panic() {
        let mut book = TicketBook::new(0, 16);
        let s = ticket_slot(book.open(ray(3, Vec3::splat(1e-30))).unwrap());
        for _ in 0..2 {
            assert_eq!(
                book.apply(s, ret([i64::MAX, i64::MIN, i64::MAX], 1), true),
                Applied::Pending
            );
        }
        // Infinite radiance (tiny weight) and negative sums are not stored.
        assert_eq!(
            book.apply(s, ret([i64::MAX, 0, 0], 1), true),
            Applied::Closed {
                entry: None,
                shading: None
            }
        );
    }

    #[test]
    fn a_ticket_left_open_behind_the_window_still_closes_once() {
        let mut book = TicketBook::new(1, usize::MAX);
        let straggler = ticket_slot(book.open(ray(2, Vec3::ONE)).unwrap());
        let early = ticket_slot(book.open(ray(1, Vec3::ONE)).unwrap());
        // Many newer tickets open and close while the straggler waits, some left open.
        let mut open = Vec::new();
        for i in 0..WINDOW + 1000 {
            let s = ticket_slot(book.open(ray(1, Vec3::ONE)).unwrap());
            if i % 1000 == 0 {
                open.push(s);
            } else {
                assert!(matches!(
                    book.apply(s, ret([1, 1, 1], 1), true),
                    Applied::Closed { entry: Some(_), .. }
                ));
            }
        }
        assert!(book.recent.len() <= WINDOW, "the window is bounded");
        assert!(book.old.contains_key(&straggler) && book.old.contains_key(&open[0]));
        assert_eq!(book.open_count(), 2 + open.len());
        assert_eq!(
            book.apply(straggler, ret([1, 1, 1], 1), true),
            Applied::Pending
        );
        assert!(matches!(
            book.apply(early, ret([1, 1, 1], 1), true),
            Applied::Closed { entry: Some(_), .. }
        ));
        assert!(matches!(
            book.apply(straggler, ret([1, 1, 1], 1), true),
            Applied::Closed { entry: Some(_), .. }
        ));
        for &s in &open {
            assert!(matches!(
                book.apply(s, ret([1, 1, 1], 1), true),
                Applied::Closed { entry: Some(_), .. }
            ));
        }
        assert_eq!(book.open_count(), 0);
        // Closed, whether in the window or moved out of it: never a second close.
        for s in [straggler, early, open[0], open[open.len() - 1]] {
            assert_eq!(book.apply(s, ret([1, 1, 1], 1), true), Applied::Unknown);
        }
    }

    #[test]
    fn limits_refuse_tickets() {
        let mut book = TicketBook::new(0, 1);
        assert_eq!(book.open(ray(0, Vec3::ONE)), Err(OpenError::NoCredit));
        book.open(ray(1, Vec3::ONE)).unwrap();
        assert_eq!(book.open(ray(1, Vec3::ONE)), Err(OpenError::TooMany));
        let last_wall = crate::ticket_id::MAX_WALLS - 1;
        let mut book = TicketBook::new(last_wall, 8);
        book.next_slot = u32::MAX;
        assert_eq!(
            book.open(ray(1, Vec3::ONE)),
            Ok(ticket_id(0, last_wall, u32::MAX))
        );
        assert_eq!(book.open(ray(1, Vec3::ONE)), Err(OpenError::Exhausted));
    }
}
