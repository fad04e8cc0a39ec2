//! A scene's memory of its streamed frames ([`crossview_core::memory`]): what the past said
//! about each pair of people, dropped when it no longer applies — on a model swap, for a
//! camera whose clock offset the watch changed (its frames now pair with other frames), and
//! (in the core) for fenced cameras, long gaps and frame ids that go backwards.
use std::sync::atomic::Ordering;

use crossview_core::memory::{Memory, MemoryConfig};

use super::clock::Offsets;

/// The memory and the camera offsets it was built under.
pub(super) struct SceneMemory {
    memory: Memory,
    offsets: Offsets,
    seen: Vec<i64>,
}

impl SceneMemory {
    pub(super) fn new(cfg: MemoryConfig, offsets: Offsets) -> Self {
        let seen = read(&offsets);
        SceneMemory {
            memory: Memory::new(cfg),
            offsets,
            seen,
        }
    }

    /// The memory for the next streamed frame: cameras whose offset changed since the last
    /// one are forgotten first.
    pub(super) fn for_frame(&mut self) -> &mut Memory {
        let now = read(&self.offsets);
        for (c, (was, is)) in self.seen.iter().zip(&now).enumerate() {
            if was != is {
                tracing::debug!(
                    camera = c,
                    from = was,
                    to = is,
                    "camera offset changed: its memory dropped"
                );
                self.memory.forget_camera(c);
            }
        }
        self.seen = now;
        &mut self.memory
    }

    /// Forgets everything (a model swap: distances of another embedding space).
    pub(super) fn clear(&mut self) {
        self.memory.clear();
    }
}

fn read(offsets: &Offsets) -> Vec<i64> {
    offsets.iter().map(|o| o.load(Ordering::Acquire)).collect()
}
