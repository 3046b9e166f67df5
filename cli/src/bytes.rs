//! Byte counts on the command line: `--memory-budget 512M`, `2GiB`, `1073741824`.
//!
//! A whole number with an optional suffix K, M, G or T (any case, optionally followed by
//! `i` and/or `B`: `64MiB`, `64MB`, `64m` are all the same). Every suffix is a power of
//! 1024, as memory is counted; a lone `B` means bytes.

/// What a byte count looks like, for error messages.
const EXPECTED: &str = "expected a whole number of bytes with an optional K, M, G or T suffix (powers of 1024), \
     e.g. 536870912, 512M or 2GiB";

/// Parse a byte count (see the module docs). The error is one line naming the input.
pub fn parse_bytes(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let digits = t.bytes().take_while(u8::is_ascii_digit).count();
    let (number, suffix) = t.split_at(digits);
    if number.is_empty() {
        return Err(format!("{s:?}: {EXPECTED}"));
    }
    let shift = match suffix.trim_start().to_ascii_lowercase().as_str() {
        "" | "b" => 0,
        "k" | "kb" | "ki" | "kib" => 10,
        "m" | "mb" | "mi" | "mib" => 20,
        "g" | "gb" | "gi" | "gib" => 30,
        "t" | "tb" | "ti" | "tib" => 40,
        _ => return Err(format!("{s:?}: {EXPECTED}")),
    };
    let n: u64 = number
        .parse()
        .map_err(|_| format!("{s:?} is too large (at most {} bytes)", u64::MAX))?;
    n.checked_mul(1u64 << shift)
        .ok_or_else(|| format!("{s:?} is too large (at most {} bytes)", u64::MAX))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plain_numbers_and_suffixes() {
        assert_eq!(parse_bytes("0"), Ok(0));
        assert_eq!(parse_bytes("1048576"), Ok(1 << 20));
        assert_eq!(parse_bytes("100B"), Ok(100));
        assert_eq!(parse_bytes("4k"), Ok(4096));
        assert_eq!(parse_bytes("512M"), Ok(512 << 20));
        assert_eq!(parse_bytes("512MB"), Ok(512 << 20));
        assert_eq!(parse_bytes("64MiB"), Ok(64 << 20));
        assert_eq!(parse_bytes("64mi"), Ok(64 << 20));
        assert_eq!(parse_bytes("2G"), Ok(2 << 30));
        assert_eq!(parse_bytes("2gib"), Ok(2 << 30));
        assert_eq!(parse_bytes("3T"), Ok(3 << 40));
        assert_eq!(parse_bytes(" 8 M "), Ok(8 << 20));
    }

    #[test]
    fn bad_input_is_a_clear_one_line_error() {
        for bad in [
            "", "M", "-1", "1.5G", "12X", "1e6", "0x10", "5 MiBs", "G2", "１２",
        ] {
            let e = parse_bytes(bad).expect_err(bad);
            assert!(e.contains(&format!("{bad:?}")), "{e}");
            assert!(e.contains("K, M, G or T"), "{e}");
            assert!(!e.contains('\n'), "{e}");
        }
        let e = parse_bytes("99999999999999999999").expect_err("overflow");
        assert!(e.contains("too large"), "{e}");
        let e = parse_bytes("17000000T").expect_err("overflow");
        assert!(e.contains("too large"), "{e}");
        assert_eq!(parse_bytes("16777215T"), Ok(16_777_215u64 << 40));
    }
}
