//! Bearer tokens.
//!
//! A token is a secret string of printable ASCII (it travels in an `authorization:
//! Bearer ...` header), at least [`MIN_LEN`] characters, read from a file (its first
//! line; a trailing newline is ignored) or an environment variable. It is compared in
//! constant time and never printed: `Debug` shows `Token(<redacted>)`, and errors name
//! the file, never its contents.

use std::fmt;
use std::io::Read;
use std::path::Path;
use std::sync::Arc;

/// Fewer characters than this make a guessable token: refused.
pub const MIN_LEN: usize = 16;
/// More than this is not a token (and is not read further).
pub const MAX_LEN: usize = 4096;

/// Why a token could not be had.
#[derive(Debug, thiserror::Error)]
pub enum CredentialError {
    #[error("cannot read the token file {path}: {message}")]
    Read { path: String, message: String },
    #[error("the token {origin} is empty")]
    Empty { origin: String },
    #[error("the token {origin} is shorter than {MIN_LEN} characters")]
    TooShort { origin: String },
    #[error("the token {origin} is longer than {MAX_LEN} bytes")]
    TooLong { origin: String },
    #[error(
        "the token {origin} holds a character that cannot travel in a header (only printable ASCII without spaces)"
    )]
    BadCharacter { origin: String },
    #[error("cannot make a random token: {0}")]
    Random(String),
}

/// A bearer token.
#[derive(Clone, PartialEq, Eq)]
pub struct Token(Arc<str>);

impl fmt::Debug for Token {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("Token(<redacted>)")
    }
}

impl Token {
    /// `text` as a token; `origin` says where it came from, for errors ("in FILE").
    pub fn parse(text: &str, origin: &str) -> Result<Token, CredentialError> {
        let t = text.strip_suffix('\n').unwrap_or(text);
        let t = t.strip_suffix('\r').unwrap_or(t);
        let origin = origin.to_string();
        if t.is_empty() {
            return Err(CredentialError::Empty { origin });
        }
        if t.len() > MAX_LEN {
            return Err(CredentialError::TooLong { origin });
        }
        if !t.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(CredentialError::BadCharacter { origin });
        }
        if t.len() < MIN_LEN {
            return Err(CredentialError::TooShort { origin });
        }
        Ok(Token(t.into()))
    }

    /// The token in `path` (read no further than [`MAX_LEN`] + 2 bytes).
    pub fn from_file(path: &Path) -> Result<Token, CredentialError> {
        let shown = path.display().to_string();
        let read_err = |message: String| CredentialError::Read {
            path: shown.clone(),
            message,
        };
        let meta = std::fs::metadata(path).map_err(|e| read_err(e.to_string()))?;
        if !meta.is_file() {
            return Err(read_err("not a regular file".into()));
        }
        let mut bytes = Vec::new();
        std::fs::File::open(path)
            .map_err(|e| read_err(e.to_string()))?
            .take(MAX_LEN as u64 + 2)
            .read_to_end(&mut bytes)
            .map_err(|e| read_err(e.to_string()))?;
        let text = String::from_utf8(bytes).map_err(|_| CredentialError::BadCharacter {
            origin: format!("in {shown}"),
        })?;
        Token::parse(&text, &format!("in {shown}"))
    }

    /// A fresh random token (256 bits, hex).
    pub fn generate() -> Result<Token, CredentialError> {
        let mut b = [0u8; 32];
        getrandom::fill(&mut b).map_err(|e| CredentialError::Random(e.to_string()))?;
        let hex: String = b.iter().map(|x| format!("{x:02x}")).collect();
        Ok(Token(hex.into()))
    }

    /// The secret itself, to write into a file for a child process.
    pub fn expose(&self) -> &str {
        &self.0
    }

    /// Whether `presented` is this token, in time that depends only on the lengths.
    pub fn matches(&self, presented: &[u8]) -> bool {
        let want = self.0.as_bytes();
        if want.len() != presented.len() {
            return false;
        }
        want.iter()
            .zip(presented)
            .fold(0u8, |acc, (a, b)| acc | (a ^ b))
            == 0
    }

    /// The `authorization` header value presenting this token.
    pub fn header(&self) -> String {
        format!("Bearer {}", self.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_checks_and_hides() {
        let t = Token::parse("0123456789abcdef\n", "in f").unwrap();
        assert!(t.matches(b"0123456789abcdef"));
        assert!(!t.matches(b"0123456789abcdeF"));
        assert!(!t.matches(b"0123456789abcde"));
        assert_eq!(format!("{t:?}"), "Token(<redacted>)");
        assert_eq!(t.header(), "Bearer 0123456789abcdef");
        assert!(matches!(
            Token::parse("short", "x"),
            Err(CredentialError::TooShort { .. })
        ));
        assert!(matches!(
            Token::parse("", "x"),
            Err(CredentialError::Empty { .. })
        ));
        assert!(matches!(
            Token::parse("0123456789 abcdef", "x"),
            Err(CredentialError::BadCharacter { .. })
        ));
        let g = Token::generate().unwrap();
        assert_eq!(g.expose().len(), 64);
        assert_ne!(g, Token::generate().unwrap());
    }

    #[test]
    fn a_file_error_names_the_file_not_its_contents() {
        let dir = std::env::temp_dir().join(format!("dray-token-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("tok");
        std::fs::write(&f, "secret words here\n").unwrap();
        let e = Token::from_file(&f).unwrap_err().to_string();
        assert!(e.contains("tok") && !e.contains("secret"), "{e}");
        let e = Token::from_file(&dir).unwrap_err().to_string();
        assert!(e.contains("not a regular file"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
