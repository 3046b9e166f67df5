//! How the coordinator quotes what a client sent in its error messages: bounded, and
//! with the scene root (a detail of its file system) written as the client gave it. A
//! leaf every module that answers a request uses, so none of them depends on
//! [`crate::validate`] for it.

/// The longest of every free-text field but `scene` (names, modes, lists of names).
pub const MAX_NAME_BYTES: usize = 256;

/// `text` quoted for an error message, cut to 80 characters: errors name the input
/// that was wrong but never echo an unbounded request (a 4 MiB field would become a
/// 4 MiB error in the caller's logs and ours).
pub fn bounded(text: &str) -> String {
    const ECHO_CHARS: usize = 80;
    if text.chars().count() <= ECHO_CHARS {
        return format!("{text:?}");
    }
    let head: String = text.chars().take(ECHO_CHARS).collect();
    format!("{head:?}... ({} bytes)", text.len())
}

/// `message` with the scene's canonical path (which starts with the coordinator's
/// scene root, a detail of its file system) written as the client gave it (issue 45,
/// item 11: API errors showed the absolute scene root).
pub fn as_given(message: &str, canonical: &str, given: &str) -> String {
    if canonical.is_empty() {
        return message.to_string();
    }
    message.replace(canonical, given)
}
