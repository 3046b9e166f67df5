//! The rule for a worker's name (`RegisterWorkerRequest.name`): the worker checks it
//! when it starts (`dray worker --name`) and the coordinator again when it registers,
//! so both say the same thing about a bad one. The name is a label for people (logs,
//! ListWorkers, the dashboard), so it is kept to characters that read the same in a
//! log line, a URL, a Kubernetes pod name and an HTML table.

/// The longest worker name, in characters (bytes: they are ASCII).
pub const MAX_WORKER_NAME: usize = 64;

/// What is wrong with a worker name.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WorkerNameError {
    /// Longer than [`MAX_WORKER_NAME`].
    #[error("{len} characters is longer than {MAX_WORKER_NAME}")]
    TooLong {
        /// Its length in characters.
        len: usize,
    },
    /// A character outside `[A-Za-z0-9._-]`.
    #[error(
        "{found:?} (character {at}) is not allowed: a name is 1 to {MAX_WORKER_NAME} of \
         A-Z a-z 0-9 . _ -"
    )]
    BadChar {
        /// The character.
        found: char,
        /// Its position, from 1.
        at: usize,
    },
}

/// Check `name`: empty (no name) or 1 to [`MAX_WORKER_NAME`] characters of
/// `[A-Za-z0-9._-]`.
pub fn check_worker_name(name: &str) -> Result<(), WorkerNameError> {
    let len = name.chars().count();
    if len > MAX_WORKER_NAME {
        return Err(WorkerNameError::TooLong { len });
    }
    match name
        .chars()
        .enumerate()
        .find(|(_, c)| !(c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-')))
    {
        Some((i, found)) => Err(WorkerNameError::BadChar { found, at: i + 1 }),
        None => Ok(()),
    }
}

/// The default name of a worker given none: the host name when it is a valid name
/// (a Kubernetes pod's host name is the pod name), else none (empty).
pub fn default_worker_name(hostname: &str) -> String {
    let h = hostname.trim();
    if check_worker_name(h).is_ok() {
        h.to_string()
    } else {
        String::new()
    }
}

/// A worker as logs and messages name it: `w3-1a2b3c4d (worker-2)`, or the id alone
/// when it has no name.
pub fn worker_label(id: &str, name: &str) -> String {
    if name.is_empty() {
        id.to_string()
    } else {
        format!("{id} ({name})")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn good_names_pass() {
        for n in ["", "worker-1", "a", "gpu_node.07", "W-9", &"x".repeat(64)] {
            assert_eq!(check_worker_name(n), Ok(()), "{n:?}");
        }
    }

    #[test]
    fn bad_names_say_what_is_wrong() {
        assert_eq!(
            check_worker_name(&"x".repeat(65)),
            Err(WorkerNameError::TooLong { len: 65 })
        );
        assert_eq!(
            check_worker_name("worker 2"),
            Err(WorkerNameError::BadChar { found: ' ', at: 7 })
        );
        assert_eq!(
            check_worker_name("nœud"),
            Err(WorkerNameError::BadChar { found: 'œ', at: 2 })
        );
        assert_eq!(
            check_worker_name("a/b"),
            Err(WorkerNameError::BadChar { found: '/', at: 2 })
        );
        // 65 multi-byte characters are counted as characters, not bytes.
        assert_eq!(
            check_worker_name(&"é".repeat(65)),
            Err(WorkerNameError::TooLong { len: 65 })
        );
        let e = check_worker_name("<b>").unwrap_err().to_string();
        assert!(e.contains("'<'") && e.contains("A-Z a-z 0-9 . _ -"), "{e}");
    }

    #[test]
    fn default_is_the_host_name_when_valid() {
        assert_eq!(default_worker_name("dray-worker-0\n"), "dray-worker-0");
        assert_eq!(default_worker_name("my host"), "");
        assert_eq!(default_worker_name(""), "");
    }

    #[test]
    fn label_names_id_and_name() {
        assert_eq!(worker_label("w3-00ab", "worker-2"), "w3-00ab (worker-2)");
        assert_eq!(worker_label("w3-00ab", ""), "w3-00ab");
    }
}
