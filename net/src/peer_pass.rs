//! Peer passes: how a worker proves who it is when it opens a ray stream to another.
//!
//! Every worker holds its own member secret, which the coordinator gave it at
//! registration (RegisterWorkerResponse.member_token). The pass for sender `A` at
//! receiver `B` is HMAC-SHA256 keyed with B's secret over A's worker id. The coordinator,
//! which knows every secret, hands A its pass for B (ClusterService.GetPeerPass, a call A
//! must make with its own secret); B recomputes the pass from its own secret and the
//! stream's claimed sender. So a stream's sender is authenticated, not claimed: holding
//! the cluster token is not enough to pose as another worker, and B never learns A's
//! secret nor A B's.

use ring::hmac;

/// What the MAC covers besides the sender's id, so that a pass can never be mistaken
/// for any other use of the same secret.
const CONTEXT: &[u8] = b"dray ray stream sender v1\0";

/// The pass for `sender_id` at the worker whose member secret is `receiver_secret`,
/// as lower-case hex.
pub fn peer_pass(receiver_secret: &str, sender_id: &str) -> String {
    let key = hmac::Key::new(hmac::HMAC_SHA256, receiver_secret.as_bytes());
    let mut ctx = hmac::Context::with_key(&key);
    ctx.update(CONTEXT);
    ctx.update(sender_id.as_bytes());
    hex(ctx.sign().as_ref())
}

/// Whether `pass` is the pass for `sender_id` at the worker holding `receiver_secret`,
/// compared in constant time.
pub fn verify_peer_pass(receiver_secret: &str, sender_id: &str, pass: &str) -> bool {
    let Some(tag) = unhex(pass) else {
        return false;
    };
    let key = hmac::Key::new(hmac::HMAC_SHA256, receiver_secret.as_bytes());
    let mut msg = Vec::with_capacity(CONTEXT.len() + sender_id.len());
    msg.extend_from_slice(CONTEXT);
    msg.extend_from_slice(sender_id.as_bytes());
    hmac::verify(&key, &msg, &tag).is_ok()
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(text: &str) -> Option<Vec<u8>> {
    if text.len() != 64 || !text.is_ascii() {
        return None;
    }
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&text[i..i + 2], 16).ok())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pass_verifies_only_for_its_sender_and_receiver() {
        let (b, c) = (
            "secret-of-worker-b-0123456789",
            "secret-of-worker-c-0123456789",
        );
        let pass = peer_pass(b, "worker-a");
        assert_eq!(pass.len(), 64);
        assert!(verify_peer_pass(b, "worker-a", &pass));
        // Another sender cannot use it, nor can it be used at another receiver.
        assert!(!verify_peer_pass(b, "worker-x", &pass));
        assert!(!verify_peer_pass(c, "worker-a", &pass));
        // Malformed passes are refused, not panicked on.
        for bad in ["", "zz", &pass[..63], &"é".repeat(32), &format!("{pass}00")] {
            assert!(!verify_peer_pass(b, "worker-a", bad), "{bad:?}");
        }
        let mut flipped = pass.clone().into_bytes();
        flipped[0] = if flipped[0] == b'0' { b'1' } else { b'0' };
        assert!(!verify_peer_pass(
            b,
            "worker-a",
            std::str::from_utf8(&flipped).unwrap()
        ));
    }
}
