//! The layout of a ticket id, the one place it is defined (workers route returns by it,
//! hosts and actors take it apart).
//!
//! `replica << 52 | wall << 32 | slot`: the slot the wall's actor issued (bits 0..31,
//! never 0), the wall (bits 32..51: a job's walls are numbered below [`MAX_WALLS`] =
//! 2^20) and, under sender placement, the replica that issued it (bits 52..63,
//! 1..=[`MAX_REPLICAS`]; 0 when each wall has one actor). A return must reach the very
//! actor that opened its ticket, and the replica bits say which process that is.
//!
//! Everything that makes or reads a ticket id goes through these functions: the wall's
//! [`TicketBook`](crate::tickets::TicketBook) (which issues replica 0), the host (which
//! sets the replica and routes returns by wall and slot) and the worker (which routes
//! returns to the host by replica or wall).

/// Bits of the wall field.
const WALL_BITS: u32 = 20;
/// Walls a ticket id can name: a job's walls are numbered `0..MAX_WALLS`.
pub const MAX_WALLS: u32 = 1 << WALL_BITS;
/// Where the replica field starts.
const REPLICA_SHIFT: u32 = 32 + WALL_BITS;
/// The most replicas a wall can have (the replica field is 12 bits; 0 means none).
pub const MAX_REPLICAS: u32 = (1 << (64 - REPLICA_SHIFT)) - 1;

/// The id of `slot` of `wall` issued by replica `replica` (0: the only actor).
pub fn ticket_id(replica: u32, wall: u32, slot: u32) -> u64 {
    u64::from(replica & MAX_REPLICAS) << REPLICA_SHIFT
        | u64::from(wall & (MAX_WALLS - 1)) << 32
        | u64::from(slot)
}

/// The wall of a ticket.
pub fn ticket_wall(ticket: u64) -> u32 {
    ((ticket >> 32) as u32) & (MAX_WALLS - 1)
}

/// The replica that issued a ticket (0: the wall's only actor).
pub fn ticket_replica(ticket: u64) -> u32 {
    (ticket >> REPLICA_SHIFT) as u32
}

/// The slot of a ticket in its actor's book.
pub fn ticket_slot(ticket: u64) -> u32 {
    ticket as u32
}

/// `ticket` as issued by `replica` (its replica field replaced).
pub fn with_replica(ticket: u64, replica: u32) -> u64 {
    ticket_id(replica, ticket_wall(ticket), ticket_slot(ticket))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_round_trip() {
        for (r, w, s) in [
            (0, 0, 1),
            (1, 7, 9),
            (MAX_REPLICAS, (1 << 20) - 1, u32::MAX),
            (4095, 123_456, 42),
        ] {
            let t = ticket_id(r, w, s);
            assert_eq!(
                (ticket_replica(t), ticket_wall(t), ticket_slot(t)),
                (r, w, s)
            );
        }
        assert_eq!(MAX_REPLICAS, 4095);
    }

    #[test]
    fn without_a_replica_the_old_layout_holds() {
        assert_eq!(ticket_id(0, 9, 4), 9u64 << 32 | 4);
        assert_eq!(with_replica(9u64 << 32 | 4, 3) >> 52, 3);
    }
}
