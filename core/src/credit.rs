//! Credit: the integer each tile starts with and its rays carry, and the arithmetic that
//! splits and sums it (docs/architecture.md "Credit").
//!
//! Each tile starts with [`Credit::TILE`]; every ray carries a share, and a tile is
//! complete when all of its credit has come back to the coordinator. A ray that spawns
//! children must give each child a non-zero share, or a child could terminate before its
//! siblings and the tile would look complete too early.
//!
//! Shares are integers, split so that deep paths do not run out: shadow and
//! ambient-occlusion rays never spawn, so each gets exactly 1; the rays that continue a
//! path (reflection, refraction, diffuse) split what is left. A path tracer's chain of
//! bounces then costs a few units per bounce instead of halving its credit every time,
//! and only branching trees (Whitted with both reflection and refraction at every hit)
//! halve it per level: with 2^62 per tile that is still dozens of levels below any real
//! job's depth. When a share cannot be split, the job fails with [`CreditError`]
//! instead of producing a wrong image.
//!
//! The same arithmetic closes ray-cache tickets: a ticket closes when the credit handed
//! back to it adds up to its ray's.
//!
//! [`Credit`] is the one type for all of it, in every actor. It becomes a bare `u64`
//! only on the wire (the ray record's first field, `Tile.credit`, `TileCredit.credit`,
//! `TicketReturn.credit`, `JobSetup.tile_credit`), through [`Credit::from_wire`] and
//! [`Credit::to_wire`].

use std::fmt;

use crate::integrator::RayKind;

/// An amount of credit: a tile's, a ray's share, or a sum of shares handed back.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[repr(transparent)]
pub struct Credit(u64);

impl Credit {
    /// No credit.
    pub const ZERO: Credit = Credit(0);

    /// The credit each tile starts with. Large, so a tile's camera rays and their
    /// descendants can split it many times before a share reaches 1 (a ray whose share
    /// cannot be split further fails the job rather than losing count); below 2^63 so
    /// sums of returned credit never overflow however they are grouped.
    pub const TILE: Credit = Credit(1 << 62);

    /// Credit as a message carries it.
    pub const fn from_wire(wire: u64) -> Credit {
        Credit(wire)
    }

    /// Credit as a message carries it.
    pub const fn to_wire(self) -> u64 {
        self.0
    }

    pub const fn is_zero(self) -> bool {
        self.0 == 0
    }

    /// `self + other`, or `None` on overflow: where credit from elsewhere is added to
    /// what is already back, an overflow means something was counted twice.
    pub const fn checked_add(self, other: Credit) -> Option<Credit> {
        match self.0.checked_add(other.0) {
            Some(c) => Some(Credit(c)),
            None => None,
        }
    }

    /// `self - other`, or `None` when `other` is larger.
    pub const fn checked_sub(self, other: Credit) -> Option<Credit> {
        match self.0.checked_sub(other.0) {
            Some(c) => Some(Credit(c)),
            None => None,
        }
    }

    /// `self + other`, at most `u64::MAX`: for gathering credit that is checked where
    /// it arrives (by the coordinator per tile, by a cache actor per ticket). Shares of
    /// one tile never add up past [`Credit::TILE`]; a sum that would (a hostile or buggy
    /// peer) stays too large to be accepted rather than wrapping to a plausible value.
    pub const fn saturating_add(self, other: Credit) -> Credit {
        Credit(self.0.saturating_add(other.0))
    }

    /// The shares of `kinds` (the children, in spawn order) from a parent with this
    /// credit, and what the parent itself hands back. The shares and the remainder
    /// always sum to `self`.
    ///
    /// A parent with children keeps one unit for itself and hands it back in the same
    /// report as its own contributions (emission, ambient light). Without that, its
    /// children's credit could reach the coordinator from another worker first, the tile
    /// would look complete, and the parent's contributions would arrive too late for the
    /// image.
    ///
    /// The shares go into `shares`, a buffer the caller reuses (it is cleared first):
    /// the tracer splits once per hit.
    #[inline]
    pub fn split_into(
        self,
        kinds: &[RayKind],
        shares: &mut Vec<Credit>,
    ) -> Result<Credit, CreditError> {
        shares.clear();
        if kinds.is_empty() {
            return Ok(self);
        }
        let credit = self.0;
        let terminal = kinds.iter().filter(|k| k.is_occlusion()).count() as u64;
        let continuing = kinds.len() as u64 - terminal;
        if credit < terminal + continuing + 1 {
            return Err(CreditError {
                credit: self,
                children: kinds.len(),
            });
        }
        if continuing == 0 {
            shares.resize(kinds.len(), Credit(1));
            return Ok(Credit(credit - terminal));
        }
        let rest = credit - terminal - 1;
        // One continuing ray (a path's next bounce) is the common case: no division.
        let (each, extra) = if continuing == 1 {
            (rest, 0)
        } else {
            (rest / continuing, rest % continuing)
        };
        let mut first = true;
        shares.extend(kinds.iter().map(|k| {
            Credit(if k.is_occlusion() {
                1
            } else if first {
                first = false;
                each + extra
            } else {
                each
            })
        }));
        Ok(Credit(1))
    }

    /// The share of camera ray `index` (0-based, of `count`) of a tile with this credit:
    /// equal shares, the first ray taking the remainder. `None` when the credit is less
    /// than `count`.
    pub fn camera_share(self, count: u64, index: u64) -> Option<Credit> {
        let credit = self.0;
        if count == 0 || credit < count || index >= count {
            return None;
        }
        let each = credit / count;
        Some(Credit(if index == 0 {
            each + credit % count
        } else {
            each
        }))
    }
}

impl fmt::Display for Credit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.0.fmt(f)
    }
}

/// A ray's credit could not give every child a share.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "a ray with credit {credit} cannot give {children} children a share each \
     (the tile's credit is exhausted by a very deep or branching ray tree)"
)]
pub struct CreditError {
    pub credit: Credit,
    pub children: usize,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// [`Credit::split_into`] with a fresh buffer, in wire units.
    fn split(credit: u64, kinds: &[RayKind]) -> Result<(Vec<u64>, u64), CreditError> {
        let mut shares = Vec::new();
        let back = Credit(credit).split_into(kinds, &mut shares)?;
        Ok((shares.iter().map(|s| s.to_wire()).collect(), back.to_wire()))
    }

    #[test]
    fn shares_sum_to_the_credit() {
        use RayKind::*;
        for credit in [5u64, 10, 1 << 40, u64::MAX] {
            for kinds in [
                vec![],
                vec![Shadow],
                vec![Shadow, Shadow, Diffuse],
                vec![Reflection, Refraction],
                vec![Shadow, Reflection, Refraction],
                vec![AmbientOcclusion; 3],
            ] {
                let (shares, back) = split(credit, &kinds).unwrap();
                assert_eq!(shares.len(), kinds.len());
                assert!(shares.iter().all(|&s| s > 0));
                assert!(kinds.is_empty() || back > 0, "the parent keeps a unit");
                let total: u128 = shares.iter().map(|&s| s as u128).sum::<u128>() + back as u128;
                assert_eq!(total, credit as u128, "{credit} {kinds:?}");
            }
        }
    }

    #[test]
    fn path_chains_cost_little_credit() {
        // A path of 1000 bounces with two lights' shadow rays per hit.
        let mut c = 1u64 << 36;
        for _ in 0..1000 {
            let (s, back) =
                split(c, &[RayKind::Shadow, RayKind::Shadow, RayKind::Diffuse]).unwrap();
            assert_eq!(back, 1);
            c = s[2];
        }
        assert_eq!(c, (1u64 << 36) - 3000);
    }

    #[test]
    fn exhausted_credit_is_an_error() {
        assert_eq!(
            split(2, &[RayKind::Reflection, RayKind::Refraction]),
            Err(CreditError {
                credit: Credit(2),
                children: 2
            })
        );
        assert_eq!(Credit(3).camera_share(4, 0), None);
        assert_eq!(Credit(10).camera_share(4, 0), Some(Credit(4)));
        assert_eq!(Credit(10).camera_share(4, 3), Some(Credit(2)));
    }

    #[test]
    fn sums_never_wrap() {
        let max = Credit::from_wire(u64::MAX);
        assert_eq!(max.checked_add(Credit(1)), None);
        assert_eq!(max.saturating_add(Credit(1)), max);
        assert_eq!(Credit(1).checked_sub(Credit(2)), None);
        assert_eq!(Credit(3).checked_sub(Credit(2)), Some(Credit(1)));
        assert_eq!(Credit::TILE.to_wire(), 1 << 62);
        assert_eq!(
            Credit::TILE.checked_add(Credit::TILE),
            Some(Credit::from_wire(1 << 63)),
            "two whole tiles' worth still fits"
        );
    }
}
