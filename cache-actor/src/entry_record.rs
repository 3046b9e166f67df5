//! A stored entry on the wire: 68 bytes, as `WallEntries.entries` and
//! `TicketAck.entries` carry them (cache.proto), so a replica of a wall can store what
//! another replica stored, bit for bit.

use glam::Vec3;

use crate::store::{Entry, EntryKey};

/// Bytes of one entry record.
pub const ENTRY_RECORD_BYTES: usize = 68;

/// Append `entry`'s record to `out`.
pub fn encode_entry(entry: &Entry, out: &mut Vec<u8>) {
    let k = &entry.key;
    out.extend_from_slice(&k.pixel.to_le_bytes());
    out.extend_from_slice(&k.sample.to_le_bytes());
    out.extend_from_slice(&k.depth.to_le_bytes());
    out.push(k.kind);
    out.push(0);
    for v in k.origin.iter().chain(&k.dir) {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for v in entry
        .point
        .iter()
        .chain(&entry.dir.to_array())
        .chain(&entry.radiance)
    {
        out.extend_from_slice(&v.to_le_bytes());
    }
}

/// Why records could not be read.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum EntryRecordError {
    #[error("{bytes} bytes of entries is not a whole number of {ENTRY_RECORD_BYTES}-byte records")]
    Length { bytes: usize },
    #[error("{records} entry records for {walls} walls")]
    Walls { records: usize, walls: usize },
}

/// The entries in `bytes`, which must hold exactly `walls` records.
pub fn decode_entries(bytes: &[u8], walls: usize) -> Result<Vec<Entry>, EntryRecordError> {
    if !bytes.len().is_multiple_of(ENTRY_RECORD_BYTES) {
        return Err(EntryRecordError::Length { bytes: bytes.len() });
    }
    let records = bytes.len() / ENTRY_RECORD_BYTES;
    if records != walls {
        return Err(EntryRecordError::Walls { records, walls });
    }
    Ok(bytes
        .chunks_exact(ENTRY_RECORD_BYTES)
        .map(decode_one)
        .collect())
}

fn decode_one(r: &[u8]) -> Entry {
    let u32_at = |i: usize| u32::from_le_bytes([r[i], r[i + 1], r[i + 2], r[i + 3]]);
    let f32_at = |i: usize| f32::from_bits(u32_at(i));
    Entry {
        key: EntryKey {
            pixel: u32_at(0),
            sample: u32_at(4),
            depth: u16::from_le_bytes([r[8], r[9]]),
            kind: r[10],
            origin: [u32_at(12), u32_at(16), u32_at(20)],
            dir: [u32_at(24), u32_at(28), u32_at(32)],
        },
        point: [f32_at(36), f32_at(40)],
        dir: Vec3::new(f32_at(44), f32_at(48), f32_at(52)),
        radiance: [f32_at(56), f32_at(60), f32_at(64)],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(i: u32) -> Entry {
        Entry {
            key: EntryKey {
                pixel: i,
                sample: i + 1,
                depth: 3,
                kind: 2,
                origin: [1.5f32.to_bits(), (-0.0f32).to_bits(), i],
                dir: [7, 8, 9],
            },
            point: [0.25, -1e-30],
            dir: Vec3::new(0.0, 0.6, 0.8),
            radiance: [1.0, f32::MIN_POSITIVE, 3e7],
        }
    }

    #[test]
    fn records_round_trip_bit_for_bit() {
        let entries: Vec<Entry> = (0..5).map(entry).collect();
        let mut bytes = Vec::new();
        for e in &entries {
            encode_entry(e, &mut bytes);
        }
        assert_eq!(bytes.len(), 5 * ENTRY_RECORD_BYTES);
        assert_eq!(decode_entries(&bytes, 5).unwrap(), entries);
    }

    #[test]
    fn bad_lengths_are_named() {
        assert_eq!(
            decode_entries(&[0; 67], 1),
            Err(EntryRecordError::Length { bytes: 67 })
        );
        assert_eq!(
            decode_entries(&[0; 68], 2),
            Err(EntryRecordError::Walls {
                records: 1,
                walls: 2
            })
        );
    }
}
