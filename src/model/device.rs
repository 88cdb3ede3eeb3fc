//! Picking the compute device at run time (`--device cpu|cuda:N`).

use candle_core::Device;

use super::ModelError;

/// Parses `cpu`, `cuda` (= `cuda:0`) or `cuda:N`. CUDA devices need the `cuda` cargo feature;
/// without it the error says so instead of failing later inside candle.
pub fn parse_device(s: &str) -> Result<Device, ModelError> {
    let s = s.trim();
    if s.eq_ignore_ascii_case("cpu") {
        return Ok(Device::Cpu);
    }
    let ordinal = match s.to_ascii_lowercase().as_str() {
        "cuda" => Some(0),
        other => other.strip_prefix("cuda:").and_then(|n| n.parse::<usize>().ok()),
    };
    let Some(ordinal) = ordinal else {
        return Err(ModelError::UnknownDevice(s.to_string()));
    };
    if cfg!(feature = "cuda") {
        Ok(Device::new_cuda(ordinal)?)
    } else {
        let _ = ordinal;
        Err(ModelError::CudaNotCompiled(s.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_cpu_and_rejects_garbage() {
        assert!(matches!(parse_device("cpu"), Ok(Device::Cpu)));
        assert!(matches!(parse_device(" CPU "), Ok(Device::Cpu)));
        assert!(matches!(parse_device("gpu"), Err(ModelError::UnknownDevice(_))));
        assert!(matches!(parse_device("cuda:x"), Err(ModelError::UnknownDevice(_))));
    }

    #[cfg(not(feature = "cuda"))]
    #[test]
    fn cuda_without_the_feature_is_a_clear_error() {
        let err = parse_device("cuda:1").unwrap_err();
        assert!(matches!(err, ModelError::CudaNotCompiled(_)));
        assert!(err.to_string().contains("`cuda` feature"), "{err}");
    }
}
