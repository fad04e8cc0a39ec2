//! The association cost model used for admission: what one frame costs before it is run.
//!
//! Association matches every pair of reported cameras with one Hungarian assignment
//! (`O(n·m·min(n, m))` for an `n × m` pair), after one encoder call over all boxes and the
//! identity step, both far cheaper at the sizes the limits allow. A frame with `n_c` boxes in
//! camera `c` therefore costs
//!
//! ```text
//! cost = Σ_{a<b} n_a · n_b · min(n_a, n_b)      (units)
//! ```
//!
//! One unit is roughly 2–3.5 ns of one core: the issue-12 probe of the release server took
//! 4.6 s for a 7 × 512 frame (2.8·10⁹ units, 1.6 ns/unit) and 40–49 s for 7 × 1024
//! (2.3·10¹⁰ units); `tests/serve/frame_cost.rs` prints the figure of the build it runs in
//! (3.4 ns/unit for 3 × 405 boxes in the test profile on a busy 2-core machine). The
//! default budget, 2·10⁸ units (well under a second), admits
//! 7 cameras × 200 boxes or 2 cameras × 580 boxes; a person seen by every one of 7 cameras
//! adds about `21 · 3 · n²` units to an `n`-person frame.

/// The cost in units of a frame whose reported cameras have `counts` boxes.
pub fn frame_cost(counts: &[usize]) -> u64 {
    let mut sorted: Vec<u64> = counts.iter().map(|&n| n as u64).collect();
    sorted.sort_unstable();
    // With counts ascending, min(n_a, n_b) = n_a for a < b: Σ_a n_a² · Σ_{b>a} n_b.
    let mut suffix: u64 = sorted.iter().sum();
    let mut cost: u64 = 0;
    for &n in &sorted {
        suffix -= n;
        cost = cost.saturating_add(n.saturating_mul(n).saturating_mul(suffix));
    }
    cost
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute(counts: &[usize]) -> u64 {
        let mut c = 0u64;
        for a in 0..counts.len() {
            for b in a + 1..counts.len() {
                let (x, y) = (counts[a] as u64, counts[b] as u64);
                c += x * y * x.min(y);
            }
        }
        c
    }

    #[test]
    fn matches_the_pairwise_sum() {
        for counts in [
            vec![],
            vec![5],
            vec![3, 4],
            vec![0, 7, 2, 9],
            vec![35; 7],
            vec![1024; 7],
        ] {
            assert_eq!(frame_cost(&counts), brute(&counts), "{counts:?}");
        }
        assert_eq!(frame_cost(&[200; 7]), 21 * 200 * 200 * 200);
    }
}
