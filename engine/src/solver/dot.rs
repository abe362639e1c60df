//! The dot products of `S = C·F`: one entry, or two sharing their vertex feature.
//!
//! Every form sums in one fixed order, so an entry's value is a fixed function of its inputs on
//! a given machine: the one form [`Kernels::detect`] picks computes every entry, whichever path
//! (memo, grid, one or two at a time) asks for it, and the grid's losses equal the rasterised
//! ones bit for bit. Machines with different instruction sets may differ in the last bits.
//!
//! The forms: AVX2 + FMA (four 8-wide FMA chains, 32 products a step), and a portable one with
//! eight lanes for any other CPU and for the tail past the last full step. One chain made a
//! 128-long dot product latency-bound; the compiler's own vectorisation of lane arrays used
//! 2-wide loads. The lanes are summed in registers, in the portable form's order. An AVX-512 form (four
//! 16-wide chains) was no faster on a Xeon that has it (a probe, not a report: the grid's
//! entries are bound by loading the features, not by the FMAs), so it was left out.

/// `a·b`.
pub(super) type Dot = fn(&[f32], &[f32]) -> f32;
/// `[a0·b, a1·b]`, each the same bits as [`Dot`] of it.
pub(super) type Dot2 = fn(&[f32], &[f32], &[f32]) -> [f32; 2];

/// The forms this CPU runs.
#[derive(Clone, Copy, Debug)]
pub(super) struct Kernels {
    pub dot: Dot,
    pub dot2: Dot2,
}

impl Kernels {
    /// AVX2 + FMA where the CPU has them, the portable form otherwise.
    pub fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
                // SAFETY: the features the functions are compiled for were just detected.
                return Kernels {
                    dot: |a, b| unsafe { x86::dot_avx2(a, b) },
                    dot2: |a0, a1, b| unsafe { x86::dot2_avx2(a0, a1, b) },
                };
            }
        }
        Kernels { dot: portable, dot2: |a0, a1, b| [portable(a0, b), portable(a1, b)] }
    }
}

/// Partial sums in eight lanes, added in a fixed order.
pub(super) fn portable(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        acc[i % 8] += x * y;
    }
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]))
}

/// What the portable form adds for the elements past the last full step: `+ 0.0` when there
/// are none (a feature dimension that is a multiple of the step), the same bits as summing an
/// empty tail.
#[inline]
fn tail(a: &[f32], b: &[f32]) -> f32 {
    if a.is_empty() { 0.0 } else { portable(a, b) }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    use super::tail;

    /// `((x0 + x4) + (x1 + x5)) + ((x2 + x6) + (x3 + x7))` of `x` and of `y`, in registers
    /// (through memory and scalar adds, the sums cost as much as a 128-long dot's products).
    #[target_feature(enable = "avx2,fma")]
    fn lanes_sum2(x: __m256, y: __m256) -> [f32; 2] {
        let half = |v: __m256| _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
        // [x0+x4 + x1+x5, x2+x6 + x3+x7, the same of y], then the two halves of each.
        let pairs = _mm_hadd_ps(half(x), half(y));
        let sums = _mm_hadd_ps(pairs, pairs);
        [_mm_cvtss_f32(sums), _mm_cvtss_f32(_mm_shuffle_ps(sums, sums, 1))]
    }

    /// `W` floats of `a` at `i` (unchecked: `i + W <= a.len()` by the callers' loop bounds).
    macro_rules! load {
        ($f:ident, $a:expr, $i:expr) => {
            // SAFETY: every caller steps `i` by whole steps below `body <= a.len()`.
            unsafe { $f($a.as_ptr().add($i)) }
        };
    }

    #[target_feature(enable = "avx2,fma")]
    pub(super) fn dot_avx2(a: &[f32], b: &[f32]) -> f32 {
        let n = a.len().min(b.len());
        let body = n - n % 32;
        let mut acc = [_mm256_setzero_ps(); 4];
        for i in (0..body).step_by(32) {
            for (k, acc) in acc.iter_mut().enumerate() {
                let (x, y) = (load!(_mm256_loadu_ps, a, i + 8 * k), load!(_mm256_loadu_ps, b, i + 8 * k));
                *acc = _mm256_fmadd_ps(x, y, *acc);
            }
        }
        let sum = _mm256_add_ps(_mm256_add_ps(acc[0], acc[1]), _mm256_add_ps(acc[2], acc[3]));
        lanes_sum2(sum, sum)[0] + tail(&a[body..n], &b[body..n])
    }

    /// [`dot_avx2`] of `a0` and of `a1` with `b`, the same operations per pair in the same
    /// order (so the same bits), with `b`'s loads shared.
    #[target_feature(enable = "avx2,fma")]
    pub(super) fn dot2_avx2(a0: &[f32], a1: &[f32], b: &[f32]) -> [f32; 2] {
        let n = b.len();
        if a0.len() != n || a1.len() != n {
            return [dot_avx2(a0, b), dot_avx2(a1, b)];
        }
        let body = n - n % 32;
        let (mut acc0, mut acc1) = ([_mm256_setzero_ps(); 4], [_mm256_setzero_ps(); 4]);
        for i in (0..body).step_by(32) {
            for k in 0..4 {
                let y = load!(_mm256_loadu_ps, b, i + 8 * k);
                acc0[k] = _mm256_fmadd_ps(load!(_mm256_loadu_ps, a0, i + 8 * k), y, acc0[k]);
                acc1[k] = _mm256_fmadd_ps(load!(_mm256_loadu_ps, a1, i + 8 * k), y, acc1[k]);
            }
        }
        let sum = |acc: [__m256; 4]| _mm256_add_ps(_mm256_add_ps(acc[0], acc[1]), _mm256_add_ps(acc[2], acc[3]));
        let [h0, h1] = lanes_sum2(sum(acc0), sum(acc1));
        [h0 + tail(&a0[body..], &b[body..]), h1 + tail(&a1[body..], &b[body..])]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vector(n: usize, seed: u32) -> Vec<f32> {
        (0..n).map(|i| (((i as u32).wrapping_mul(2654435761) ^ seed) % 1000) as f32 / 500.0 - 1.0).collect()
    }

    /// Every form agrees with the portable one to rounding, and its pair form with itself bit
    /// for bit, at lengths with and without a tail.
    #[test]
    fn forms_agree() {
        let k = Kernels::detect();
        for n in [1, 7, 31, 32, 64, 100, 128, 130, 200] {
            let (a0, a1, b) = (vector(n, 1), vector(n, 2), vector(n, 3));
            let [x0, x1] = (k.dot2)(&a0, &a1, &b);
            assert_eq!(x0.to_bits(), (k.dot)(&a0, &b).to_bits(), "n {n}");
            assert_eq!(x1.to_bits(), (k.dot)(&a1, &b).to_bits(), "n {n}");
            let exact: f64 = a0.iter().zip(&b).map(|(x, y)| f64::from(*x) * f64::from(*y)).sum();
            assert!((f64::from(x0) - exact).abs() < 1e-4 * n as f64, "n {n}: {x0} vs {exact}");
            assert!((f64::from(portable(&a0, &b)) - exact).abs() < 1e-4 * n as f64);
        }
    }
}
