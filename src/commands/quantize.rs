//! `meshstream quantize`: writes a model folder's linear layers in a GGUF block type, so that
//! `serve` and `reconstruct` load them quantized without quantizing at every start.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use meshstream::model::Quantize;
use meshstream::model::quantize::{QUANTIZED_WEIGHTS_FILE, export_quantized};

use super::out;

#[derive(Args)]
pub struct QuantizeArgs {
    /// Model folder with f32 weights (config.json + model.safetensors).
    #[arg(long, default_value = "models/default")]
    model: PathBuf,
    /// Block type: q8_0 or q4k.
    #[arg(long)]
    quantize: Quantize,
    /// Folder to write config.json and model.gguf to (not the f32 model's own).
    #[arg(long, short)]
    out: PathBuf,
}

pub fn run(args: &QuantizeArgs) -> anyhow::Result<()> {
    let report = export_quantized(&args.model, &args.out, args.quantize).with_context(|| {
        format!("quantizing {} into {}", args.model.display(), args.out.display())
    })?;
    out(format_args!("{report}"))?;
    out(format_args!("wrote {}", args.out.join(QUANTIZED_WEIGHTS_FILE).display()))
}
