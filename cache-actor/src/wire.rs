//! The cache wire codes, defined once for both ends: the option bits of a lookup
//! (cache.proto `CacheLookups.options`) and the outcome codes of an answer
//! (`CacheAnswers.outcomes`). The worker builds lookups and reads answers with these;
//! the wall actors read options and write outcomes with them (`actor::Outcome::code`).

/// Lookup option bit 0: the ray may be answered from the cache.
pub const OPTION_ANSWER: u32 = 1;
/// Lookup option bit 1: on a miss, open a ticket for the ray.
pub const OPTION_TICKET: u32 = 2;
/// Lookup option bit 2: consult the wall's hit map.
pub const OPTION_PHM: u32 = 4;
/// Lookup option bit 3: the ray can carry one more ticket, so a hit map that shades
/// (`phm.shade`) may open one to learn the radiance it returns. Ignored by maps that
/// do not shade.
pub const OPTION_ROOM: u32 = 8;

/// Outcome: not answered, no ticket; the ray goes on exactly.
pub const CODE_MISS: u8 = 0;
/// Outcome: answered; the radiance follows in `CacheAnswers.radiance`.
pub const CODE_HIT: u8 = 1;
/// Outcome: not answered; the ray carries on the ticket in `CacheAnswers.tickets`.
pub const CODE_TICKET: u8 = 2;
/// Outcome: the hit map predicts a miss; the ray skips the domain behind the wall.
pub const CODE_SKIP: u8 = 3;
/// Outcome: the hit map predicts a hit for an occlusion ray; it is occluded.
pub const CODE_OCCLUDED: u8 = 4;
/// Outcome: the hit map predicts a hit and shades (`phm.shade`): the ray is answered
/// with the cell's mean radiance, which follows in `CacheAnswers.radiance` as a hit's.
pub const CODE_SHADED: u8 = 5;
/// Added to [`CODE_MISS`] or [`CODE_TICKET`] when the ray goes on as a probe.
pub const PROBE: u8 = 8;
