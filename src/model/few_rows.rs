//! A linear layer on a few rows, on the CPU: every weight row is read once for all of them.
//!
//! Why: a decode step of a few sequences (one whole mesh's candidates, a few streams) multiplies
//! each layer's weights by 1 to 4 rows, and reading the weights is nearly all of that work.
//! candle's gemm reads them at memory speed for one row but took twice as long for 2 to 4
//! rows; this kernel takes about as long for four rows as for one (`docs/decisions.md`, "A few
//! rows multiply in a kernel of their own").

use std::sync::atomic::{AtomicBool, Ordering};

use candle_core::{Layout, Storage, Tensor};

use super::Result;

/// The most rows multiplied here, in one pass over the weights.
pub const MAX_ROWS: usize = 4;

static ENABLED: AtomicBool = AtomicBool::new(true);

/// Whether layers of few rows take the kernel: always, unless a benchmark turns it off to
/// measure the general path beside it in one run (`meshstream bench decode`).
pub fn set_enabled(enabled: bool) {
    ENABLED.store(enabled, Ordering::Relaxed);
}

/// x (rows, in) W^T + bias for W (out, in) and bias (out), f32 on the CPU, contiguous;
/// `None` where the kernel does not apply (more than [`MAX_ROWS`] rows, other dtypes or
/// layouts, `in` not a multiple of 8, a CPU without AVX2 and FMA), for the general path.
pub fn linear(x: &Tensor, weight: &Tensor, bias: Option<&Tensor>) -> Result<Option<Tensor>> {
    let (rows, input) = x.dims2()?;
    let (out, weight_input) = weight.dims2()?;
    let enabled = ENABLED.load(Ordering::Relaxed) && kernel::available();
    if !(1..=MAX_ROWS).contains(&rows) || weight_input != input || !enabled {
        return Ok(None);
    }
    let (x_storage, x_layout) = x.storage_and_layout();
    let (w_storage, w_layout) = weight.storage_and_layout();
    let b = bias.map(|b| b.storage_and_layout());
    let (Some(xs), Some(ws)) = (f32_slice(&x_storage, x_layout), f32_slice(&w_storage, w_layout))
    else {
        return Ok(None);
    };
    let bs = match &b {
        Some((storage, layout)) => match f32_slice(storage, layout) {
            Some(bs) if bs.len() == out => Some(bs),
            _ => return Ok(None),
        },
        None => None,
    };
    let Some(y) = kernel::multiply(xs, ws, bs, input) else { return Ok(None) };
    Ok(Some(Tensor::from_vec(y, (rows, out), x.device())?))
}

/// The elements of a contiguous f32 tensor on the CPU.
fn f32_slice<'a>(storage: &'a Storage, layout: &Layout) -> Option<&'a [f32]> {
    let Storage::Cpu(cpu) = storage else { return None };
    let (start, end) = layout.contiguous_offsets()?;
    cpu.as_slice::<f32>().ok()?.get(start..end)
}

#[cfg(target_arch = "x86_64")]
mod kernel {
    use std::arch::x86_64::*;

    pub fn available() -> bool {
        is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma")
    }

    /// x (rows, input) W^T + bias, W (out, input), both row-major; `None` unless `input` is a
    /// positive multiple of 8 that divides both, at most [`super::MAX_ROWS`] rows, and this
    /// CPU has AVX2 and FMA.
    pub fn multiply(x: &[f32], w: &[f32], bias: Option<&[f32]>, input: usize) -> Option<Vec<f32>> {
        if input == 0
            || !input.is_multiple_of(8)
            || !x.len().is_multiple_of(input)
            || !w.len().is_multiple_of(input)
        {
            return None;
        }
        let (rows, out) = (x.len() / input, w.len() / input);
        if !(1..=super::MAX_ROWS).contains(&rows) || bias.is_some_and(|b| b.len() != out) {
            return None;
        }
        if !available() {
            return None;
        }
        let mut y = vec![0f32; rows * out];
        // SAFETY: the CPU has AVX2 and FMA (checked above), and the sizes are as `tile`
        // requires: x holds `rows` rows and w `out` rows of `input`, a multiple of 8, and y
        // holds rows x out.
        unsafe {
            match rows {
                1 => tile::<1, 8>(x, w, &mut y, input, out),
                2 => tile::<2, 4>(x, w, &mut y, input, out),
                3 => tile::<3, 3>(x, w, &mut y, input, out),
                _ => tile::<4, 2>(x, w, &mut y, input, out),
            }
        }
        if let Some(bias) = bias {
            for row in y.chunks_exact_mut(out) {
                for (v, b) in row.iter_mut().zip(bias) {
                    *v += b;
                }
            }
        }
        Some(y)
    }

    /// All M rows of x against O weight rows at a time (M x O sums of 8 lanes in registers),
    /// then the weight rows left over one at a time.
    ///
    /// # Safety
    /// AVX2 and FMA; x.len() == M * input, w.len() == out * input, y.len() == M * out, and
    /// `input` a multiple of 8.
    #[target_feature(enable = "avx2,fma")]
    unsafe fn tile<const M: usize, const O: usize>(
        x: &[f32],
        w: &[f32],
        y: &mut [f32],
        input: usize,
        out: usize,
    ) {
        let mut o = 0;
        while o + O <= out {
            // SAFETY: o + O <= out, and the rest as this function requires.
            unsafe { block::<M, O>(x, w, y, input, out, o) };
            o += O;
        }
        for o in o..out {
            // SAFETY: o < out.
            unsafe { block::<M, 1>(x, w, y, input, out, o) };
        }
    }

    /// y[r][o..o + O] for every row r of x.
    ///
    /// # Safety
    /// As [`tile`], and o + O <= out.
    #[target_feature(enable = "avx2,fma")]
    unsafe fn block<const M: usize, const O: usize>(
        x: &[f32],
        w: &[f32],
        y: &mut [f32],
        input: usize,
        out: usize,
        o: usize,
    ) {
        let (xp, wp) = (x.as_ptr(), w.as_ptr());
        let mut sums = [[_mm256_setzero_ps(); O]; M];
        for c in (0..input).step_by(8) {
            let mut xs = [_mm256_setzero_ps(); M];
            for (r, v) in xs.iter_mut().enumerate() {
                // SAFETY: r < M and c + 8 <= input.
                *v = unsafe { _mm256_loadu_ps(xp.add(r * input + c)) };
            }
            for k in 0..O {
                // SAFETY: o + k < out and c + 8 <= input.
                let wv = unsafe { _mm256_loadu_ps(wp.add((o + k) * input + c)) };
                for (row, &xv) in sums.iter_mut().zip(&xs) {
                    row[k] = _mm256_fmadd_ps(wv, xv, row[k]);
                }
            }
        }
        for (r, row) in sums.iter().enumerate() {
            for (k, &sum) in row.iter().enumerate() {
                y[r * out + o + k] = horizontal_sum(sum);
            }
        }
    }

    #[target_feature(enable = "avx2,fma")]
    fn horizontal_sum(v: __m256) -> f32 {
        let s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
        let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
        _mm_cvtss_f32(_mm_add_ss(s, _mm_shuffle_ps(s, s, 1)))
    }
}

#[cfg(not(target_arch = "x86_64"))]
mod kernel {
    pub fn available() -> bool {
        false
    }

    pub fn multiply(_: &[f32], _: &[f32], _: Option<&[f32]>, _: usize) -> Option<Vec<f32>> {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::testing::max_abs_diff;
    use candle_core::{Device, Tensor};

    fn general(x: &Tensor, w: &Tensor, b: Option<&Tensor>) -> Tensor {
        let y = x.matmul(&w.t().unwrap()).unwrap();
        match b {
            Some(b) => y.broadcast_add(b).unwrap(),
            None => y,
        }
    }

    #[test]
    fn matches_the_general_matmul_for_every_row_count_and_leftover_outputs() {
        if !kernel::available() {
            eprintln!("skipped: this CPU has no AVX2 and FMA, and the kernel does not run");
            return;
        }
        let dev = Device::Cpu;
        for (out, input) in [(1, 8), (7, 24), (13, 256), (768, 256), (9, 1024)] {
            let w = Tensor::randn(0f32, 1.0, (out, input), &dev).unwrap();
            let b = Tensor::randn(0f32, 1.0, out, &dev).unwrap();
            for rows in 1..=MAX_ROWS {
                let x = Tensor::randn(0f32, 1.0, (rows, input), &dev).unwrap();
                for bias in [None, Some(&b)] {
                    let y = linear(&x, &w, bias).unwrap().expect("the kernel applies");
                    let tolerance = 1e-5 * input as f32;
                    let gap = max_abs_diff(&y, &general(&x, &w, bias));
                    assert!(gap < tolerance, "{rows} x {input} -> {out}: {gap}");
                }
            }
        }
    }

    #[test]
    fn leaves_what_it_does_not_take_to_the_general_path() {
        let dev = Device::Cpu;
        let w = Tensor::randn(0f32, 1.0, (16, 24), &dev).unwrap();
        let rows = |n: usize| Tensor::randn(0f32, 1.0, (n, 24), &dev).unwrap();
        // Too many rows; a width that is not a multiple of 8; another dtype; a transposed view.
        assert!(linear(&rows(MAX_ROWS + 1), &w, None).unwrap().is_none());
        let narrow = Tensor::randn(0f32, 1.0, (2, 12), &dev).unwrap();
        let w12 = Tensor::randn(0f32, 1.0, (16, 12), &dev).unwrap();
        assert!(linear(&narrow, &w12, None).unwrap().is_none());
        let f64_rows = rows(2).to_dtype(candle_core::DType::F64).unwrap();
        assert!(
            linear(&f64_rows, &w.to_dtype(candle_core::DType::F64).unwrap(), None)
                .unwrap()
                .is_none()
        );
        let transposed = Tensor::randn(0f32, 1.0, (24, 2), &dev).unwrap().t().unwrap();
        assert!(linear(&transposed, &w, None).unwrap().is_none());
        // A bias of the wrong length, and weights that do not take the rows' width.
        let short = Tensor::zeros(3, candle_core::DType::F32, &dev).unwrap();
        assert!(linear(&rows(2), &w, Some(&short)).unwrap().is_none());
        assert!(linear(&rows(2), &w12, None).unwrap().is_none());
    }
}
