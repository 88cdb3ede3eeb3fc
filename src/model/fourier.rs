//! Fourier features of points and normals: each input coordinate kept raw plus a sine and a
//! cosine per octave, so the encoder can resolve detail far below the input's unit scale.

use candle_core::{D, Device, Tensor};

use super::Result;

#[derive(Debug, Clone)]
pub struct FourierFeatures {
    /// (F,) angular frequencies pi * 2^i.
    freqs: Tensor,
}

impl FourierFeatures {
    pub fn new(octaves: usize, device: &Device) -> Result<Self> {
        let freqs: Vec<f32> =
            (0..octaves).map(|i| std::f32::consts::PI * 2f32.powi(i as i32)).collect();
        Ok(Self { freqs: Tensor::from_vec(freqs, octaves, device)? })
    }

    /// x (B, M, C) -> (B, M, C * (2F + 1)).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let x = x.unsqueeze(D::Minus1)?;
        let angles = x.broadcast_mul(&self.freqs)?;
        let features = Tensor::cat(&[&x, &angles.sin()?, &angles.cos()?], D::Minus1)?;
        Ok(features.flatten_from(2)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn width_and_values() {
        let dev = Device::Cpu;
        let ff = FourierFeatures::new(2, &dev).unwrap();
        let x = Tensor::from_vec(vec![0.5f32, 0.0], (1, 1, 2), &dev).unwrap();
        let y = ff.forward(&x).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(y.len(), 2 * 5);
        // First channel: raw, sin(pi/2), sin(pi), cos(pi/2), cos(pi).
        let expect = [0.5, 1.0, 0.0, 0.0, -1.0];
        for (a, b) in y[..5].iter().zip(expect) {
            assert!((a - b).abs() < 1e-5, "{y:?}");
        }
    }
}
