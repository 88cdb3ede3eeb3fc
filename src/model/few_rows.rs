//! A linear layer on a few rows, on the CPU: every weight row is read once for all of them.
//!
//! Why: a decode step of a few sequences (one whole mesh's candidates, a few streams, the face
//! beam's partial faces) multiplies each layer's weights by a few rows, and reading the
//! weights is nearly all of that work. candle's gemm reads them at memory speed for one row
//! but took twice as long for 2 to 4 rows; this kernel takes about as long for four rows as
//! for one, and reads the weights once for every four rows up to 8. It also reads weights
//! stored as f16, half the bytes, where a layer's f32 weights are f16 values (the shipped
//! model's are): the same products, sooner (`docs/decisions.md`, "A few rows multiply in a
//! kernel of their own").

use std::sync::atomic::{AtomicBool, Ordering};

use candle_core::{DType, Layout, Storage, Tensor};
use half::f16;

use super::Result;

/// The most rows multiplied here, four a pass over the weights. Why 8: parts of 5 to 8 rows
/// (a batch of 16 on two threads, the face beam's partial faces of 2 rows) decoded 1.2x
/// faster than with gemm, while gemm multiplies more rows well.
pub const MAX_ROWS: usize = 8;

static ENABLED: AtomicBool = AtomicBool::new(true);

/// Whether layers of few rows take the kernel: always, unless a benchmark turns it off to
/// measure the general path beside it in one run (`meshstream bench decode`).
pub fn set_enabled(enabled: bool) {
    ENABLED.store(enabled, Ordering::Relaxed);
}

/// x (rows, in) W^T + bias for W (out, in) and bias (out) on the CPU, contiguous, all f32 but
/// W, which may be f16; `None` where the kernel does not apply (more than [`MAX_ROWS`] rows,
/// other dtypes or layouts, `in` not a multiple of 8, a CPU without AVX2, FMA and F16C), for
/// the general path.
pub fn linear(x: &Tensor, weight: &Tensor, bias: Option<&Tensor>) -> Result<Option<Tensor>> {
    let (rows, input) = x.dims2()?;
    let (out, weight_input) = weight.dims2()?;
    if !(1..=MAX_ROWS).contains(&rows) || weight_input != input || !ENABLED.load(Ordering::Relaxed)
    {
        return Ok(None);
    }
    let (x_storage, x_layout) = x.storage_and_layout();
    let (w_storage, w_layout) = weight.storage_and_layout();
    let b = bias.map(|b| b.storage_and_layout());
    let Some(xs) = slice::<f32>(&x_storage, x_layout) else { return Ok(None) };
    let bs = match &b {
        Some((storage, layout)) => match slice::<f32>(storage, layout) {
            Some(bs) if bs.len() == out => Some(bs),
            _ => return Ok(None),
        },
        None => None,
    };
    let (ws, wl) = (&w_storage, w_layout);
    let y = match weight.dtype() {
        DType::F32 => slice(ws, wl).and_then(|w: &[f32]| kernel::multiply(xs, w, bs, input)),
        DType::F16 => slice(ws, wl).and_then(|w: &[f16]| kernel::multiply(xs, w, bs, input)),
        _ => None,
    };
    let Some(y) = y else { return Ok(None) };
    Ok(Some(Tensor::from_vec(y, (rows, out), x.device())?))
}

/// `weight` in f16 when every value of it is an f16 value (`None` otherwise, or off the CPU):
/// the same layer for [`linear`] in half the bytes.
pub fn exact_f16(weight: &Tensor) -> Result<Option<Tensor>> {
    if !weight.device().is_cpu() || weight.dtype() != DType::F32 {
        return Ok(None);
    }
    let values = weight.flatten_all()?.to_vec1::<f32>()?;
    if values.iter().any(|&v| f16::from_f32(v).to_f32().to_bits() != v.to_bits()) {
        return Ok(None);
    }
    Ok(Some(weight.to_dtype(DType::F16)?.contiguous()?))
}

/// The elements of a contiguous tensor of `T` on the CPU.
fn slice<'a, T: candle_core::WithDType>(storage: &'a Storage, layout: &Layout) -> Option<&'a [T]> {
    let Storage::Cpu(cpu) = storage else { return None };
    let (start, end) = layout.contiguous_offsets()?;
    cpu.as_slice::<T>().ok()?.get(start..end)
}

#[cfg(target_arch = "x86_64")]
mod kernel {
    use std::arch::x86_64::*;

    use half::f16;

    /// Whether this CPU runs the kernel: AVX2, FMA and F16C.
    pub fn available() -> bool {
        is_x86_feature_detected!("avx2")
            && is_x86_feature_detected!("fma")
            && is_x86_feature_detected!("f16c")
    }

    /// A weight's element type: f32 as it is, or f16 widened to f32 as it is loaded.
    pub trait Weight: Copy {
        /// Eight weights from `at` as f32.
        ///
        /// # Safety
        /// Eight elements readable from `at`; a CPU that runs the kernel ([`available`]).
        unsafe fn load8(at: *const Self) -> __m256;
    }

    impl Weight for f32 {
        #[inline(always)]
        unsafe fn load8(at: *const f32) -> __m256 {
            // SAFETY: as the caller guarantees.
            unsafe { _mm256_loadu_ps(at) }
        }
    }

    impl Weight for f16 {
        #[inline(always)]
        unsafe fn load8(at: *const f16) -> __m256 {
            // SAFETY: as the caller guarantees; 8 f16 are 128 bits.
            unsafe { _mm256_cvtph_ps(_mm_loadu_si128(at.cast())) }
        }
    }

    /// x (rows, input) W^T + bias, W (out, input), both row-major; `None` unless `input` is a
    /// positive multiple of 8 that divides both, at most [`super::MAX_ROWS`] rows, and this
    /// CPU runs the kernel.
    pub fn multiply<W: Weight>(
        x: &[f32],
        w: &[W],
        bias: Option<&[f32]>,
        input: usize,
    ) -> Option<Vec<f32>> {
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
        // Four rows a pass over the weights: their sums fill the registers.
        for (x, y) in x.chunks(4 * input).zip(y.chunks_mut(4 * out)) {
            // SAFETY: the CPU runs the kernel (checked above), and the sizes are as
            // `tile` requires: x holds 1 to 4 rows and w `out` rows of `input`, a multiple of
            // 8, and y as many rows of `out`.
            unsafe {
                match x.len() / input {
                    1 => tile::<W, 1, 8>(x, w, y, input, out),
                    2 => tile::<W, 2, 4>(x, w, y, input, out),
                    3 => tile::<W, 3, 3>(x, w, y, input, out),
                    _ => tile::<W, 4, 2>(x, w, y, input, out),
                }
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
    /// A CPU that runs the kernel ([`available`]); x.len() == M * input, w.len() == out *
    /// input, y.len() == M * out, and `input` a multiple of 8.
    #[target_feature(enable = "avx2,fma,f16c")]
    unsafe fn tile<W: Weight, const M: usize, const O: usize>(
        x: &[f32],
        w: &[W],
        y: &mut [f32],
        input: usize,
        out: usize,
    ) {
        let mut o = 0;
        while o + O <= out {
            // SAFETY: o + O <= out, and the rest as this function requires.
            unsafe { block::<W, M, O>(x, w, y, input, out, o) };
            o += O;
        }
        for o in o..out {
            // SAFETY: o < out.
            unsafe { block::<W, M, 1>(x, w, y, input, out, o) };
        }
    }

    /// y[r][o..o + O] for every row r of x.
    ///
    /// # Safety
    /// As [`tile`], and o + O <= out.
    #[target_feature(enable = "avx2,fma,f16c")]
    unsafe fn block<W: Weight, const M: usize, const O: usize>(
        x: &[f32],
        w: &[W],
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
                let wv = unsafe { W::load8(wp.add((o + k) * input + c)) };
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
    #[cfg(test)]
    pub fn available() -> bool {
        false
    }

    /// A weight's element type (the kernel is x86-64 only).
    pub trait Weight {}
    impl Weight for f32 {}
    impl Weight for half::f16 {}

    pub fn multiply<W: Weight>(
        _: &[f32],
        _: &[W],
        _: Option<&[f32]>,
        _: usize,
    ) -> Option<Vec<f32>> {
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
            eprintln!("skipped: this CPU has no AVX2, FMA and F16C, and the kernel does not run");
            return;
        }
        let dev = Device::Cpu;
        for (out, input) in [(1, 8), (7, 24), (13, 256), (768, 256), (9, 1024)] {
            // f16 values, so that the layer also multiplies from its f16 copy.
            let w = Tensor::randn(0f32, 1.0, (out, input), &dev).unwrap();
            let w = w.to_dtype(DType::F16).unwrap().to_dtype(DType::F32).unwrap();
            let w16 = exact_f16(&w).unwrap().expect("f16 values");
            let b = Tensor::randn(0f32, 1.0, out, &dev).unwrap();
            for rows in 1..=MAX_ROWS {
                let x = Tensor::randn(0f32, 1.0, (rows, input), &dev).unwrap();
                for (weight, bias) in [(&w, None), (&w, Some(&b)), (&w16, Some(&b))] {
                    let y = linear(&x, weight, bias).unwrap().expect("the kernel applies");
                    let tolerance = 1e-5 * input as f32;
                    let gap = max_abs_diff(&y, &general(&x, &w, bias));
                    let dtype = weight.dtype();
                    assert!(gap < tolerance, "{rows} x {input} -> {out}, {dtype:?}: {gap}");
                }
            }
        }
    }

    #[test]
    fn an_f16_copy_only_of_weights_that_are_f16_values() {
        let dev = Device::Cpu;
        let halves =
            Tensor::new(&[[0.5f32, -2.0, 1.0 / 1024.0], [65504.0, 0.0, 3.0]], &dev).unwrap();
        let copy = exact_f16(&halves).unwrap().expect("every value is an f16");
        assert_eq!(copy.dtype(), DType::F16);
        assert_eq!(max_abs_diff(&copy.to_dtype(DType::F32).unwrap(), &halves), 0.0);
        // 0.1 and 65,520 are not f16 values; f64 and f16 weights are not copied.
        for values in [[0.1f32, 1.0], [65_520.0, 1.0]] {
            assert!(exact_f16(&Tensor::new(&values, &dev).unwrap()).unwrap().is_none());
        }
        assert!(exact_f16(&halves.to_dtype(DType::F64).unwrap()).unwrap().is_none());
        assert!(exact_f16(&copy).unwrap().is_none());
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
        let f64_rows = rows(2).to_dtype(DType::F64).unwrap();
        assert!(linear(&f64_rows, &w.to_dtype(DType::F64).unwrap(), None).unwrap().is_none());
        let transposed = Tensor::randn(0f32, 1.0, (24, 2), &dev).unwrap().t().unwrap();
        assert!(linear(&transposed, &w, None).unwrap().is_none());
        // A bias of the wrong length, and weights that do not take the rows' width.
        let short = Tensor::zeros(3, DType::F32, &dev).unwrap();
        assert!(linear(&rows(2), &w, Some(&short)).unwrap().is_none());
        assert!(linear(&rows(2), &w12, None).unwrap().is_none());
    }
}
