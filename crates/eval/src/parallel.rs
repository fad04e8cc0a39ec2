//! Frames dealt to worker threads, results taken back in frame order: the offline tools
//! (`crossview associate`, `crossview eval`) use every core and still produce exactly what one
//! thread would.
//!
//! Item `i` goes to worker `i % n`; each worker sends its results, in its own order, into its
//! own bounded channel ([`std::sync::mpsc::sync_channel`]), and the caller's thread takes them
//! back from worker `0, 1, …, n-1, 0, 1, …` in turn. That is the items' order without a reorder
//! buffer, and a worker never runs more than `window` results ahead of the consumer, so memory
//! stays bounded however long the input. Dealing round-robin instead of on demand keeps the
//! order trivial; the window absorbs the frame-to-frame variation of the work.
use std::num::NonZeroUsize;
use std::sync::mpsc::{Receiver, sync_channel};

/// Results a worker may hold ahead of the consumer (per worker) in [`map_ordered`] callers of
/// this crate.
pub const DEFAULT_WINDOW: usize = 8;

/// Worker threads to use: `requested`, else the machine's available parallelism (1 when unknown).
pub fn worker_count(requested: Option<NonZeroUsize>) -> usize {
    requested
        .or_else(|| std::thread::available_parallelism().ok())
        .map_or(1, NonZeroUsize::get)
}

/// Runs `work(state, index, item)` for every item, on one thread per element of `states` (item
/// `i` on `states[i % states.len()]`), and hands the results to `sink(index, result)` on the
/// calling thread **in item order**. With one state everything runs on the calling thread.
///
/// `work` must give the same result for an item whichever state runs it (one encoder session
/// each, of the same model): then the sink sees exactly what a single-threaded loop would.
/// At most `window` (at least 1) results per worker wait for the sink.
///
/// The first error in item order stops the run and is returned (the same error a
/// single-threaded loop would return, since the items before it succeeded); an error of the
/// sink stops it too. Workers stop at their first error or when the sink stopped. A panic in a
/// worker is propagated to the caller.
///
/// Panics when `states` is empty.
pub fn map_ordered<T, S, R, E, W, K>(
    items: &[T],
    states: &mut [S],
    window: usize,
    work: W,
    mut sink: K,
) -> Result<(), E>
where
    T: Sync,
    S: Send,
    R: Send,
    E: Send,
    W: Fn(&mut S, usize, &T) -> Result<R, E> + Sync,
    K: FnMut(usize, R) -> Result<(), E>,
{
    assert!(!states.is_empty(), "map_ordered needs at least one worker");
    if states.len() == 1 || items.len() <= 1 {
        let state = &mut states[0];
        for (i, item) in items.iter().enumerate() {
            sink(i, work(state, i, item)?)?;
        }
        return Ok(());
    }
    let n = states.len().min(items.len());
    let work = &work;
    std::thread::scope(|scope| {
        let mut handles = Vec::with_capacity(n);
        let mut receivers: Vec<Receiver<Result<R, E>>> = Vec::with_capacity(n);
        for (w, state) in states.iter_mut().take(n).enumerate() {
            let (tx, rx) = sync_channel(window.max(1));
            receivers.push(rx);
            handles.push(scope.spawn(move || {
                for i in (w..items.len()).step_by(n) {
                    let result = work(state, i, &items[i]);
                    let failed = result.is_err();
                    // A closed channel means the consumer stopped: nothing more is wanted.
                    if tx.send(result).is_err() || failed {
                        break;
                    }
                }
            }));
        }
        let mut outcome = Ok(());
        let mut lost = None;
        for i in 0..items.len() {
            let Ok(result) = receivers[i % n].recv() else {
                // The worker ended without this item's result: it panicked (an error would
                // have been received first). The join below re-raises its panic.
                lost = Some(i);
                break;
            };
            if let Err(e) = result.and_then(|r| sink(i, r)) {
                outcome = Err(e);
                break;
            }
        }
        // Unblock workers waiting on a full channel, then wait for them.
        drop(receivers);
        for h in handles {
            if let Err(panic) = h.join() {
                std::panic::resume_unwind(panic);
            }
        }
        if let Some(i) = lost {
            panic!("map_ordered: a worker ended without the result of item {i}");
        }
        outcome
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// Uneven work (item-dependent sleeps) must not change the order the sink sees.
    #[test]
    fn results_come_back_in_item_order() {
        let items: Vec<u64> = (0..200).collect();
        for workers in [1, 2, 3, 7] {
            let mut states = vec![0usize; workers];
            let mut seen = Vec::new();
            map_ordered(
                &items,
                &mut states,
                2,
                |done: &mut usize, i, &x| {
                    if x % 7 == 0 {
                        std::thread::sleep(Duration::from_millis(2));
                    }
                    *done += 1;
                    Ok::<_, String>((i, x * x))
                },
                |i, r| {
                    assert_eq!(r.0, i);
                    seen.push(r.1);
                    Ok(())
                },
            )
            .unwrap();
            let expected: Vec<u64> = items.iter().map(|x| x * x).collect();
            assert_eq!(seen, expected, "{workers} workers");
            assert_eq!(states.iter().sum::<usize>(), items.len());
            if workers > 1 {
                assert!(
                    states.iter().all(|&d| d > 0),
                    "every worker did some: {states:?}"
                );
            }
        }
    }

    #[test]
    fn the_first_error_in_item_order_wins() {
        let items: Vec<usize> = (0..50).collect();
        for workers in [1, 2, 4] {
            let mut states = vec![(); workers];
            let mut seen = 0;
            let err = map_ordered(
                &items,
                &mut states,
                1,
                |_, _, &x| {
                    // Item 31 fails fast; item 17 (another worker for 2 and 4) fails slowly.
                    if x == 17 {
                        std::thread::sleep(Duration::from_millis(20));
                        return Err(format!("item {x}"));
                    }
                    if x == 31 {
                        return Err(format!("item {x}"));
                    }
                    Ok(x)
                },
                |_, _| {
                    seen += 1;
                    Ok(())
                },
            )
            .unwrap_err();
            assert_eq!((err.as_str(), seen), ("item 17", 17), "{workers} workers");
        }
    }

    #[test]
    fn a_sink_error_stops_the_workers() {
        let items: Vec<usize> = (0..10_000).collect();
        let mut states = vec![0usize; 3];
        let err = map_ordered(
            &items,
            &mut states,
            4,
            |n: &mut usize, _, &x| {
                *n += 1;
                Ok(x)
            },
            |i, _| if i == 5 { Err("full disk") } else { Ok(()) },
        )
        .unwrap_err();
        assert_eq!(err, "full disk");
        // Bounded: each worker got at most its window (+1 in hand, +1 blocked) past item 5.
        let done: usize = states.iter().sum();
        assert!(done <= 6 + 3 * 6, "workers ran ahead: {done}");
    }

    #[test]
    #[should_panic(expected = "boom")]
    fn a_worker_panic_reaches_the_caller() {
        let items: Vec<usize> = (0..20).collect();
        let _ = map_ordered(
            &items,
            &mut [(), ()],
            2,
            |_, _, &x| {
                if x == 9 {
                    panic!("boom");
                }
                Ok::<_, ()>(x)
            },
            |_, _| Ok(()),
        );
    }

    #[test]
    fn worker_count_defaults_to_the_machine() {
        assert_eq!(worker_count(NonZeroUsize::new(3)), 3);
        assert!(worker_count(None) >= 1);
    }
}
