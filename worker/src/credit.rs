//! Splitting a ray's credit among its children (docs/architecture.md "Credit").
//!
//! Each tile starts with a fixed credit; every ray carries a share, and a tile is
//! complete when all of its credit has come back to the coordinator. A ray that spawns
//! children must give each child a non-zero share, or a child could terminate before its
//! siblings and the tile would look complete too early.
//!
//! Shares are integers, split so that deep paths do not run out: shadow and
//! ambient-occlusion rays never spawn, so each gets exactly 1; the rays that continue a
//! path (reflection, refraction, diffuse) split what is left. A path tracer's chain of
//! bounces then costs a few units per bounce instead of halving its credit every time,
//! and only branching trees (Whitted with both reflection and refraction at every hit)
//! halve it per level: with the coordinator's 2^62 per tile that is still dozens of
//! levels below any real job's depth. When a share cannot be split, the job fails with
//! [`CreditError`] instead of producing a wrong image.

use dray_core::integrator::RayKind;

/// A ray's credit could not give every child a share.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "a ray with credit {credit} cannot give {children} children a share each \
     (the tile's credit is exhausted by a very deep or branching ray tree)"
)]
pub struct CreditError {
    pub credit: u64,
    pub children: usize,
}

/// The shares of `kinds` (the children, in spawn order) from a parent's `credit`, and
/// what the parent itself hands back. The shares and the remainder always sum to
/// `credit`.
///
/// A parent with children keeps one unit for itself and hands it back in the same
/// report as its own contributions (emission, ambient light). Without that, its
/// children's credit could reach the coordinator from another worker first, the tile
/// would look complete, and the parent's contributions would arrive too late for the
/// image.
///
/// The shares go into `shares`, a buffer the caller reuses (it is cleared first): the
/// tracer splits once per hit.
#[inline]
pub fn split_into(
    credit: u64,
    kinds: &[RayKind],
    shares: &mut Vec<u64>,
) -> Result<u64, CreditError> {
    shares.clear();
    if kinds.is_empty() {
        return Ok(credit);
    }
    let terminal = kinds.iter().filter(|k| k.is_occlusion()).count() as u64;
    let continuing = kinds.len() as u64 - terminal;
    if credit < terminal + continuing + 1 {
        return Err(CreditError {
            credit,
            children: kinds.len(),
        });
    }
    if continuing == 0 {
        shares.resize(kinds.len(), 1);
        return Ok(credit - terminal);
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
        if k.is_occlusion() {
            1
        } else if first {
            first = false;
            each + extra
        } else {
            each
        }
    }));
    Ok(1)
}

/// The share of camera ray `index` (0-based, of `count`) of a tile with `credit`: equal
/// shares, the first ray taking the remainder. `None` when `credit < count`.
pub fn camera_share(credit: u64, count: u64, index: u64) -> Option<u64> {
    if count == 0 || credit < count || index >= count {
        return None;
    }
    let each = credit / count;
    Some(if index == 0 {
        each + credit % count
    } else {
        each
    })
}

#[cfg(test)]
mod tests {
    /// [`split_into`] with a fresh buffer.
    fn split(credit: u64, kinds: &[RayKind]) -> Result<(Vec<u64>, u64), CreditError> {
        let mut shares = Vec::new();
        let back = split_into(credit, kinds, &mut shares)?;
        Ok((shares, back))
    }

    use super::*;

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
                credit: 2,
                children: 2
            })
        );
        assert_eq!(camera_share(3, 4, 0), None);
        assert_eq!(camera_share(10, 4, 0), Some(4));
        assert_eq!(camera_share(10, 4, 3), Some(2));
    }
}
