//! Sets of ray kinds, and the one way their lists are written: the `kinds` knobs of ray
//! caches and hit maps (`JobSpec.ray_cache.kinds`, `JobSpec.phm.kinds`, and the CLI's
//! `--ray-cache kinds=...` / `--phm kinds=...`).
//!
//! A list is kind names ([`RayKind::name`]) separated by `,`, as render.proto documents,
//! blanks around names ignored and empty entries skipped. (The command line joins names
//! with `+` because `,` separates its `key=value` pairs; the CLI writes its lists with
//! `,` before they reach a JobSpec.) The coordinator, the worker and the cache actor all
//! read lists here, so none of them can accept a list another refuses.

use crate::integrator::RayKind;

/// A set of ray kinds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct KindSet(u8);

/// A name in a kinds list that is not one of the kinds allowed there.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{name:?} is not one of {allowed}")]
pub struct NotAKind {
    /// The name as written.
    pub name: String,
    /// The kinds allowed, listed for the message.
    pub allowed: String,
}

impl KindSet {
    /// What a hit map serves when its list is empty: shadow rays (the source's use).
    pub fn phm_default() -> KindSet {
        KindSet::of(&[RayKind::Shadow])
    }

    /// What a ray cache looks up when its list is empty: every kind that carries
    /// radiance ([`RayKind::RADIANCE`]).
    pub fn cache_default() -> KindSet {
        KindSet::of(&RayKind::RADIANCE)
    }

    /// The set of `kinds`.
    pub fn of(kinds: &[RayKind]) -> KindSet {
        KindSet(kinds.iter().fold(0, |m, k| m | 1 << *k as u8))
    }

    /// The kinds of `list` (see the module's doc), each of which must be in `allowed`;
    /// an empty list (or one of separators only) is the empty set, for the caller to
    /// give its default.
    pub fn parse(list: &str, allowed: &[RayKind]) -> Result<KindSet, NotAKind> {
        let mut set = KindSet::default();
        for name in list.split(',').map(str::trim) {
            if name.is_empty() {
                continue;
            }
            match RayKind::from_name(name).filter(|k| allowed.contains(k)) {
                Some(k) => set.0 |= 1 << k as u8,
                None => {
                    return Err(NotAKind {
                        name: name.to_string(),
                        allowed: RayKind::help_list(allowed),
                    });
                }
            }
        }
        Ok(set)
    }

    /// The kinds of `list`, or `default` when it names none (empty, or separators
    /// only): the one rule every kinds knob follows.
    pub fn parse_or(
        list: &str,
        allowed: &[RayKind],
        default: KindSet,
    ) -> Result<KindSet, NotAKind> {
        let set = KindSet::parse(list, allowed)?;
        Ok(if set.is_empty() { default } else { set })
    }

    /// Whether `kind` is in the set.
    pub fn contains(self, kind: RayKind) -> bool {
        self.0 & (1 << kind as u8) != 0
    }

    pub fn is_empty(self) -> bool {
        self.0 == 0
    }

    /// The set as a bit mask, bit `kind as u8` for each kind in it.
    pub fn bits(self) -> u8 {
        self.0
    }

    /// The set written as a list: names in [`RayKind::ALL`]'s order, joined with `,`
    /// (the JobSpec's canonical form, without duplicates).
    pub fn names(self) -> String {
        RayKind::ALL
            .iter()
            .filter(|k| self.contains(**k))
            .map(|k| k.name())
            .collect::<Vec<_>>()
            .join(",")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lists_split_on_commas_and_write_back_in_canonical_order() {
        let s = KindSet::parse(" diffuse, camera,,diffuse ", &RayKind::RADIANCE).expect("kinds");
        assert_eq!(s.names(), "camera,diffuse");
        assert!(s.contains(RayKind::Camera) && !s.contains(RayKind::Shadow));
        assert_eq!(s, KindSet::of(&[RayKind::Diffuse, RayKind::Camera]));
        assert!(
            KindSet::parse(" , ,", &RayKind::ALL)
                .expect("empty")
                .is_empty()
        );
        let e = KindSet::parse("camera+diffuse", &RayKind::RADIANCE).unwrap_err();
        assert_eq!(
            e.name, "camera+diffuse",
            "the command line's joiner is not the JobSpec's"
        );
    }

    #[test]
    fn a_list_naming_no_kind_means_the_default() {
        let shadow = KindSet::phm_default();
        for empty in ["", " ", " , ,"] {
            assert_eq!(KindSet::parse_or(empty, &RayKind::ALL, shadow), Ok(shadow));
        }
        let camera = KindSet::parse_or("camera", &RayKind::ALL, shadow).expect("kinds");
        assert_eq!(camera, KindSet::of(&[RayKind::Camera]));
        assert!(KindSet::parse_or("light", &RayKind::ALL, shadow).is_err());
    }

    #[test]
    fn a_kind_not_allowed_or_unknown_is_named_in_the_error() {
        let e = KindSet::parse("camera,shadow", &RayKind::RADIANCE).unwrap_err();
        assert_eq!(e.name, "shadow");
        assert!(e.to_string().contains("camera, reflection"), "{e}");
        let e = KindSet::parse("ao", &RayKind::ALL).unwrap_err();
        assert_eq!(e.name, "ao");
    }
}
