//! Encoded images shared by everyone who asks for the same one.
//!
//! GetImage, WatchImage and the dashboard's image endpoint used to encode a job's image
//! once per caller: 50 unread WatchImage streams on a 2048² job held 3.0 GB, 200 readers
//! of a 512² job took 240 CPU-seconds and made the job itself eight times slower (issue
//! 45, item 4). Now each job keeps the few encodings asked for last, keyed by what
//! decides their bytes (the pass, final or not, the format and the display transform),
//! and a caller that asks for one being made waits for it instead of making another.
//! The bytes are shared (`Bytes`: a stream's queued message is a reference, not a copy),
//! and at most [`encode_permits`] encodes run at once on the whole coordinator.

use std::sync::{Arc, Mutex, OnceLock};

use prost::bytes::Bytes;
use tokio::sync::{OnceCell, Semaphore};

/// Encodings a job keeps: enough for a few displays watching one pass at different
/// exposures, few enough that a job's memory stays a small multiple of one image.
const KEPT: usize = 4;

/// What decides an encoding's bytes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ImageKey {
    /// Passes in the image, and whether it is the final one.
    pub passes_done: u32,
    pub final_image: bool,
    /// The format (`ImageFormat` as its number).
    pub format: i32,
    /// The display transform, as text (exposure and tone curve: the PNG's only other
    /// inputs; an EXR ignores it, and its key carries an empty string).
    pub display: String,
}

type Slot = Arc<OnceCell<Bytes>>;

/// One job's recent encodings.
#[derive(Default)]
pub struct ImageMemo {
    slots: Mutex<Vec<(ImageKey, Slot)>>,
}

impl ImageMemo {
    /// The encoding for `key`: the one kept, the one being made (waited for), or the
    /// one `encode` makes now (under a coordinator-wide permit). An error is not kept:
    /// the next caller tries again.
    pub async fn get_or_encode<F, Fut, E>(&self, key: ImageKey, encode: F) -> Result<Bytes, E>
    where
        F: FnOnce() -> Fut,
        Fut: std::future::Future<Output = Result<Bytes, E>>,
    {
        let slot = self.slot(key);
        slot.get_or_try_init(|| async {
            // The semaphore is never closed, so acquire cannot fail; an error would only
            // mean running without a permit.
            let _permit = encode_permits().acquire().await.ok();
            encode().await
        })
        .await
        .cloned()
    }

    /// The slot for `key`, made (and the oldest beyond [`KEPT`] forgotten) if new.
    fn slot(&self, key: ImageKey) -> Slot {
        let mut slots = dray_sync::lock(&self.slots);
        if let Some((_, s)) = slots.iter().find(|(k, _)| *k == key) {
            return s.clone();
        }
        let s = Slot::default();
        slots.push((key, s.clone()));
        if slots.len() > KEPT {
            slots.remove(0);
        }
        s
    }

    /// How many encodings the job holds (tests).
    pub fn len(&self) -> usize {
        dray_sync::lock(&self.slots).len()
    }

    /// Whether it holds none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The coordinator-wide bound on image encodes running at once: half the cores (at
/// least one), so watchers of many jobs cannot take the CPU the jobs need.
pub fn encode_permits() -> &'static Semaphore {
    static PERMITS: OnceLock<Semaphore> = OnceLock::new();
    PERMITS.get_or_init(|| {
        let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
        Semaphore::new((cores / 2).max(1))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};

    fn key(passes: u32, display: &str) -> ImageKey {
        ImageKey {
            passes_done: passes,
            final_image: false,
            format: 1,
            display: display.into(),
        }
    }

    /// 64 callers at once for one image: one encode, every caller the same bytes
    /// (shared, not copied); another display is another encode; old keys are dropped.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn one_encode_per_key_shared_by_every_caller() {
        let memo = Arc::new(ImageMemo::default());
        let encodes = Arc::new(AtomicUsize::new(0));
        let mut calls = tokio::task::JoinSet::new();
        for _ in 0..64 {
            let (memo, encodes) = (memo.clone(), encodes.clone());
            calls.spawn(async move {
                memo.get_or_encode(key(3, "auto"), || async {
                    encodes.fetch_add(1, Ordering::SeqCst);
                    tokio::time::sleep(std::time::Duration::from_millis(20)).await;
                    Ok::<_, String>(Bytes::from(vec![7u8; 1 << 20]))
                })
                .await
                .expect("encoded")
            });
        }
        let mut first: Option<Bytes> = None;
        while let Some(b) = calls.join_next().await {
            let b = b.expect("task");
            if let Some(f) = &first {
                assert_eq!(f.as_ptr(), b.as_ptr(), "the bytes were copied");
            }
            first = Some(b);
        }
        assert_eq!(encodes.load(Ordering::SeqCst), 1);
        // An error is not kept; another key is another encode.
        let e = memo
            .get_or_encode(key(3, "+1"), || async {
                Err::<Bytes, _>("disk".to_string())
            })
            .await;
        assert!(e.is_err());
        let again = memo
            .get_or_encode(key(3, "+1"), || async {
                Ok::<_, String>(Bytes::from_static(b"x"))
            })
            .await;
        assert_eq!(again.expect("encoded").as_ref(), b"x");
        for p in 4..10 {
            memo.get_or_encode(key(p, "auto"), || async { Ok::<_, String>(Bytes::new()) })
                .await
                .expect("encoded");
        }
        assert_eq!(memo.len(), KEPT);
    }
}
