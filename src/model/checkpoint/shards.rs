//! A model folder's weights on disk, in either of the two Hugging Face layouts: one
//! `model.safetensors`, or, when the weights pass a size limit, shards
//! `model-00001-of-0000N.safetensors` ... with `model.safetensors.index.json` naming the shard
//! of every tensor. Shards keep each file under a transfer limit (uploads, object stores);
//! readers get the same tensors from either layout, and a folder holds only one of them.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::ffi::OsStr;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use super::{ModelError, Result, io_err};

/// The weights of an unsharded model folder.
pub const WEIGHTS_FILE: &str = "model.safetensors";
/// The index of a sharded model folder: which shard holds which tensor.
pub const WEIGHTS_INDEX_FILE: &str = "model.safetensors.index.json";
/// Tensor data per shard by default: 15 MiB keeps a shard, with its safetensors header, under
/// a 16 MiB transfer limit.
pub const DEFAULT_MAX_SHARD_BYTES: u64 = 15 * 1024 * 1024;

/// The tensors of a model folder, with the file they were read from (`model.safetensors` or
/// the index) for error messages.
#[derive(Debug)]
pub struct ModelWeights {
    pub path: PathBuf,
    pub tensors: HashMap<String, Tensor>,
}

/// `model.safetensors.index.json`, as the Hugging Face convention writes it.
#[derive(Serialize, Deserialize)]
struct ShardIndex {
    #[serde(default)]
    metadata: IndexMetadata,
    /// Tensor name to shard file name.
    weight_map: BTreeMap<String, String>,
}

#[derive(Default, Serialize, Deserialize)]
struct IndexMetadata {
    /// Tensor data bytes over all shards (headers not counted).
    #[serde(default)]
    total_size: u64,
}

/// Which layout a model folder holds, with the file to start reading from.
enum Layout {
    Single(PathBuf),
    Sharded(PathBuf),
}

fn layout(dir: &Path) -> Result<Layout> {
    let single = dir.join(WEIGHTS_FILE);
    let index = dir.join(WEIGHTS_INDEX_FILE);
    match (single.is_file(), index.is_file()) {
        (true, true) => Err(ModelError::MixedWeightLayouts { dir: dir.to_path_buf() }),
        (true, false) => Ok(Layout::Single(single)),
        (false, true) => Ok(Layout::Sharded(index)),
        (false, false) => Err(ModelError::Io {
            path: single,
            error: std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
        }),
    }
}

/// Reads the weights of the model folder `dir`, from `model.safetensors` or from the index and
/// its shards. Every tensor of a sharded folder must be in exactly the shard the index names.
pub fn read_model_weights(dir: &Path, device: &Device) -> Result<ModelWeights> {
    match layout(dir)? {
        Layout::Single(path) => {
            let tensors = read_safetensors(&path, device)?;
            Ok(ModelWeights { path, tensors })
        }
        Layout::Sharded(index) => read_sharded(dir, &index, device),
    }
}

/// The files holding the weights of `dir`: `model.safetensors`, or the shards in index order
/// (their names sorted, which for `model-0000I-of-0000N` names is shard order). Hashing these
/// files in this order fingerprints a folder without parsing its tensors.
pub fn weight_files(dir: &Path) -> Result<Vec<PathBuf>> {
    match layout(dir)? {
        Layout::Single(path) => Ok(vec![path]),
        Layout::Sharded(index_path) => {
            let index = read_index(&index_path)?;
            shard_names(&index).into_iter().map(|s| shard_path(dir, &index_path, s)).collect()
        }
    }
}

fn read_safetensors(path: &Path, device: &Device) -> Result<HashMap<String, Tensor>> {
    candle_core::safetensors::load(path, device).map_err(|e| ModelError::BadCheckpoint {
        path: path.to_path_buf(),
        message: cut_off_tensor(path).unwrap_or_else(|| e.to_string()),
    })
}

/// For a file that cannot be read: which tensor its end cuts off, when a truncated copy is
/// why (safetensors only says that the file does not cover its header's tensors).
fn cut_off_tensor(path: &Path) -> Option<String> {
    let bytes = std::fs::read(path).ok()?;
    let header_len = usize::try_from(u64::from_le_bytes(bytes.get(..8)?.try_into().ok()?)).ok()?;
    let header_end = header_len.checked_add(8)?;
    let header: HashMap<String, serde_json::Value> =
        serde_json::from_slice(bytes.get(8..header_end)?).ok()?;
    let data = bytes.len() - header_end;
    let (start, end, name) = header
        .iter()
        .filter_map(|(name, info)| {
            let offsets = info.get("data_offsets")?;
            let (start, end) = (offsets.get(0)?.as_u64()?, offsets.get(1)?.as_u64()?);
            (end > data as u64).then_some((start, end, name))
        })
        .min()?;
    Some(format!(
        "the file is truncated: tensor {name} (data bytes {start}..{end}) is cut off at byte \
         {data} of the data"
    ))
}

fn read_index(path: &Path) -> Result<ShardIndex> {
    let text = std::fs::read_to_string(path).map_err(io_err(path))?;
    let bad = |message: String| ModelError::BadShardIndex { path: path.to_path_buf(), message };
    let index: ShardIndex = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
    // A shard is a file beside the index: a path could read weights from anywhere.
    match index.weight_map.values().find(|s| Path::new(s).file_name() != Some(OsStr::new(s))) {
        Some(shard) => Err(bad(format!("shard {shard:?} is not a file name"))),
        None => Ok(index),
    }
}

/// The distinct shards of an index, sorted.
fn shard_names(index: &ShardIndex) -> BTreeSet<&str> {
    index.weight_map.values().map(String::as_str).collect()
}

fn shard_path(dir: &Path, index_path: &Path, shard: &str) -> Result<PathBuf> {
    let path = dir.join(shard);
    if !path.is_file() {
        return Err(ModelError::MissingShard {
            path: index_path.to_path_buf(),
            shard: shard.to_string(),
        });
    }
    Ok(path)
}

fn read_sharded(dir: &Path, index_path: &Path, device: &Device) -> Result<ModelWeights> {
    let index = read_index(index_path)?;
    let mut found: HashMap<String, (Tensor, &str)> = HashMap::new();
    for shard in shard_names(&index) {
        let tensors = read_safetensors(&shard_path(dir, index_path, shard)?, device)?;
        for (name, tensor) in tensors {
            if let Some((_, first)) = found.get(&name) {
                return Err(ModelError::DuplicateTensor {
                    path: index_path.to_path_buf(),
                    name,
                    first: first.to_string(),
                    second: shard.to_string(),
                });
            }
            found.insert(name, (tensor, shard));
        }
    }
    check_weight_map(index_path, &index.weight_map, &found)?;
    let tensors = found.into_iter().map(|(name, (tensor, _))| (name, tensor)).collect();
    Ok(ModelWeights { path: index_path.to_path_buf(), tensors })
}

/// The index and the shards must agree tensor for tensor: a tensor where the index does not
/// put it is either stale or from another model.
fn check_weight_map(
    index_path: &Path,
    weight_map: &BTreeMap<String, String>,
    found: &HashMap<String, (Tensor, &str)>,
) -> Result<()> {
    for (name, shard) in weight_map {
        if found.get(name).map(|(_, s)| *s) != Some(shard.as_str()) {
            return Err(ModelError::TensorNotInShard {
                path: index_path.to_path_buf(),
                name: name.clone(),
                shard: shard.clone(),
            });
        }
    }
    let unindexed = found
        .iter()
        .filter(|(name, _)| !weight_map.contains_key(*name))
        .map(|(name, (_, shard))| (name, shard))
        .min();
    match unindexed {
        Some((name, shard)) => Err(ModelError::BadShardIndex {
            path: index_path.to_path_buf(),
            message: format!("shard {shard} holds tensor {name:?}, which the index does not name"),
        }),
        None => Ok(()),
    }
}

/// Writes `weights` into `dir` (which must exist): one `model.safetensors` when their data
/// fits `max_shard_bytes`, else shards and an index. Weight files of the other layout, and
/// shards of an earlier export, are removed so that a reader never sees two sets of weights.
/// Returns the files written.
pub(crate) fn write_weights(
    dir: &Path,
    weights: &HashMap<String, Tensor>,
    max_shard_bytes: u64,
) -> Result<Vec<PathBuf>> {
    let shards = plan_shards(weights, max_shard_bytes);
    let written = if shards.len() <= 1 {
        let path = dir.join(WEIGHTS_FILE);
        candle_core::safetensors::save(weights, &path)?;
        vec![path]
    } else {
        write_shards(dir, weights, &shards)?
    };
    remove_stale(dir, &written)?;
    Ok(written)
}

fn data_bytes(tensor: &Tensor) -> u64 {
    (tensor.elem_count() * tensor.dtype().size_in_bytes()) as u64
}

/// Tensor names per shard: in sorted name order, each shard filled until the next tensor would
/// take it past `max_bytes`; a tensor larger than that gets a shard of its own.
fn plan_shards(weights: &HashMap<String, Tensor>, max_bytes: u64) -> Vec<Vec<&str>> {
    let mut names: Vec<&str> = weights.keys().map(String::as_str).collect();
    names.sort_unstable();
    let mut shards: Vec<Vec<&str>> = Vec::new();
    let mut filled = 0u64;
    for name in names {
        let bytes = data_bytes(&weights[name]);
        match shards.last_mut() {
            Some(shard) if filled.saturating_add(bytes) <= max_bytes => {
                shard.push(name);
                filled += bytes;
            }
            _ => {
                shards.push(vec![name]);
                filled = bytes;
            }
        }
    }
    shards
}

fn shard_file_name(number: usize, count: usize) -> String {
    format!("model-{number:05}-of-{count:05}.safetensors")
}

/// Whether `name` is a shard's file name, `model-I-of-N.safetensors` with I and N digits.
fn is_shard_file_name(name: &str) -> bool {
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    name.strip_prefix("model-")
        .and_then(|rest| rest.strip_suffix(".safetensors"))
        .and_then(|rest| rest.split_once("-of-"))
        .is_some_and(|(number, count)| digits(number) && digits(count))
}

fn write_shards(
    dir: &Path,
    weights: &HashMap<String, Tensor>,
    shards: &[Vec<&str>],
) -> Result<Vec<PathBuf>> {
    let mut index = ShardIndex {
        metadata: IndexMetadata { total_size: weights.values().map(data_bytes).sum() },
        weight_map: BTreeMap::new(),
    };
    let mut written = Vec::with_capacity(shards.len() + 1);
    for (i, names) in shards.iter().enumerate() {
        let file = shard_file_name(i + 1, shards.len());
        let shard: HashMap<&str, Tensor> =
            names.iter().map(|name| (*name, weights[*name].clone())).collect();
        let path = dir.join(&file);
        candle_core::safetensors::save(&shard, &path)?;
        index.weight_map.extend(names.iter().map(|name| (name.to_string(), file.clone())));
        written.push(path);
    }
    let path = dir.join(WEIGHTS_INDEX_FILE);
    let json = serde_json::to_string_pretty(&index)
        .map_err(|e| ModelError::BadShardIndex { path: path.clone(), message: e.to_string() })?;
    std::fs::write(&path, json).map_err(io_err(&path))?;
    written.push(path);
    Ok(written)
}

/// Removes the weight files in `dir` (either layout's) that are not among `written`.
fn remove_stale(dir: &Path, written: &[PathBuf]) -> Result<()> {
    for entry in std::fs::read_dir(dir).map_err(io_err(dir))? {
        let path = entry.map_err(io_err(dir))?.path();
        let Some(name) = path.file_name().and_then(OsStr::to_str) else { continue };
        let weights =
            name == WEIGHTS_FILE || name == WEIGHTS_INDEX_FILE || is_shard_file_name(name);
        if weights && !written.contains(&path) {
            std::fs::remove_file(&path).map_err(io_err(&path))?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::DType;

    /// Tensors "a".."e" of 4, 4, 8, 2 and 4 f32 values (16, 16, 32, 8, 16 bytes).
    fn weights() -> HashMap<String, Tensor> {
        [("a", 4), ("b", 4), ("c", 8), ("d", 2), ("e", 4)]
            .into_iter()
            .map(|(name, n)| {
                let values: Vec<f32> = (0..n).map(|i| (i * 10 + name.len()) as f32).collect();
                (name.to_string(), Tensor::new(values, &Device::Cpu).unwrap())
            })
            .collect()
    }

    fn files(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    fn assert_same(a: &HashMap<String, Tensor>, b: &HashMap<String, Tensor>) {
        let mut names: Vec<&String> = a.keys().collect();
        names.sort();
        let mut other: Vec<&String> = b.keys().collect();
        other.sort();
        assert_eq!(names, other);
        for name in names {
            let values = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            assert_eq!(values(&a[name]), values(&b[name]), "{name}");
        }
    }

    /// A folder with `weights()` in shards of at most 32 bytes: {a, b}, {c}, {d, e}.
    fn sharded() -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        write_weights(dir.path(), &weights(), 32).unwrap();
        dir
    }

    fn index_of(dir: &Path) -> serde_json::Value {
        let text = std::fs::read_to_string(dir.join(WEIGHTS_INDEX_FILE)).unwrap();
        serde_json::from_str(&text).unwrap()
    }

    fn set_index(dir: &Path, index: &serde_json::Value) {
        std::fs::write(dir.join(WEIGHTS_INDEX_FILE), index.to_string()).unwrap();
    }

    #[test]
    fn shards_fill_greedily_in_name_order_and_a_big_tensor_stands_alone() {
        let w = weights();
        assert_eq!(plan_shards(&w, 32), vec![vec!["a", "b"], vec!["c"], vec!["d", "e"]]);
        assert_eq!(
            plan_shards(&w, 20),
            vec![vec!["a"], vec!["b"], vec!["c"], vec!["d"], vec!["e"]]
        );
        assert_eq!(plan_shards(&w, 88), vec![vec!["a", "b", "c", "d", "e"]]);
        assert!(is_shard_file_name(&shard_file_name(2, 3)));
        assert!(!is_shard_file_name("model-x-of-00003.safetensors"));
        assert!(!is_shard_file_name(WEIGHTS_FILE));
    }

    #[test]
    fn weights_that_fit_are_one_file_as_before() {
        let dir = tempfile::tempdir().unwrap();
        let written = write_weights(dir.path(), &weights(), 88).unwrap();
        assert_eq!(written, vec![dir.path().join(WEIGHTS_FILE)]);
        assert_eq!(files(dir.path()), vec![WEIGHTS_FILE]);
        let plain = dir.path().join("plain.safetensors");
        candle_core::safetensors::save(&weights(), &plain).unwrap();
        assert_eq!(
            std::fs::read(&plain).unwrap(),
            std::fs::read(dir.path().join(WEIGHTS_FILE)).unwrap()
        );
        let read = read_model_weights(dir.path(), &Device::Cpu).unwrap();
        assert_eq!(read.path, dir.path().join(WEIGHTS_FILE));
        assert_same(&read.tensors, &weights());
        assert_eq!(weight_files(dir.path()).unwrap(), vec![dir.path().join(WEIGHTS_FILE)]);
    }

    #[test]
    fn sharded_weights_read_back_the_same() {
        let dir = sharded();
        assert_eq!(
            files(dir.path()),
            vec![
                "model-00001-of-00003.safetensors",
                "model-00002-of-00003.safetensors",
                "model-00003-of-00003.safetensors",
                WEIGHTS_INDEX_FILE,
            ]
        );
        let index = index_of(dir.path());
        assert_eq!(index["metadata"]["total_size"], 88);
        assert_eq!(index["weight_map"]["b"], "model-00001-of-00003.safetensors");
        assert_eq!(index["weight_map"]["c"], "model-00002-of-00003.safetensors");
        let read = read_model_weights(dir.path(), &Device::Cpu).unwrap();
        assert_eq!(read.path, dir.path().join(WEIGHTS_INDEX_FILE));
        assert_same(&read.tensors, &weights());
        let shards: Vec<PathBuf> =
            (1..=3).map(|i| dir.path().join(shard_file_name(i, 3))).collect();
        assert_eq!(weight_files(dir.path()).unwrap(), shards);
    }

    #[test]
    fn a_new_export_removes_the_other_layout_and_stale_shards() {
        let dir = sharded();
        write_weights(dir.path(), &weights(), 1 << 20).unwrap();
        assert_eq!(files(dir.path()), vec![WEIGHTS_FILE]);
        write_weights(dir.path(), &weights(), 32).unwrap();
        write_weights(dir.path(), &weights(), 56).unwrap();
        assert_eq!(
            files(dir.path()),
            vec![
                "model-00001-of-00002.safetensors",
                "model-00002-of-00002.safetensors",
                WEIGHTS_INDEX_FILE,
            ]
        );
        assert_same(&read_model_weights(dir.path(), &Device::Cpu).unwrap().tensors, &weights());
    }

    #[test]
    fn a_truncated_file_names_the_tensor_it_cuts_off() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(WEIGHTS_FILE);
        let tensors: HashMap<String, Tensor> = [("a", 16), ("b", 16)]
            .into_iter()
            .map(|(n, len)| (n.to_string(), Tensor::zeros(len, DType::F32, &Device::Cpu).unwrap()))
            .collect();
        candle_core::safetensors::save(&tensors, &path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        // The last tensor's data is the file's last 64 bytes: cut into it.
        std::fs::write(&path, &bytes[..bytes.len() - 10]).unwrap();
        let err = read_model_weights(dir.path(), &Device::Cpu).unwrap_err().to_string();
        assert!(
            err.contains("truncated") && err.contains("tensor b (data bytes 64..128)"),
            "{err}"
        );
    }

    #[test]
    fn both_layouts_at_once_are_refused() {
        let dir = sharded();
        candle_core::safetensors::save(&weights(), dir.path().join(WEIGHTS_FILE)).unwrap();
        let err = read_model_weights(dir.path(), &Device::Cpu).unwrap_err();
        assert!(matches!(err, ModelError::MixedWeightLayouts { .. }), "{err}");
    }

    #[test]
    fn a_missing_shard_is_named() {
        let dir = sharded();
        std::fs::remove_file(dir.path().join(shard_file_name(2, 3))).unwrap();
        let err = read_model_weights(dir.path(), &Device::Cpu).unwrap_err();
        assert!(
            matches!(&err, ModelError::MissingShard { shard, .. } if *shard == shard_file_name(2, 3)),
            "{err}"
        );
        let err = weight_files(dir.path()).unwrap_err();
        assert!(matches!(err, ModelError::MissingShard { .. }), "{err}");
    }

    #[test]
    fn a_malformed_index_is_refused() {
        let dir = sharded();
        std::fs::write(dir.path().join(WEIGHTS_INDEX_FILE), "{\"weight_map\": [1, 2]}").unwrap();
        let err = read_model_weights(dir.path(), &Device::Cpu).unwrap_err();
        assert!(matches!(err, ModelError::BadShardIndex { .. }), "{err}");

        let dir = sharded();
        let mut index = index_of(dir.path());
        index["weight_map"]["a"] = "../model-00001-of-00003.safetensors".into();
        set_index(dir.path(), &index);
        let err = read_model_weights(dir.path(), &Device::Cpu).unwrap_err();
        assert!(matches!(err, ModelError::BadShardIndex { .. }), "{err}");
    }

    #[test]
    fn a_tensor_in_two_shards_is_refused() {
        let dir = sharded();
        let path = dir.path().join(shard_file_name(3, 3));
        let mut third = candle_core::safetensors::load(&path, &Device::Cpu).unwrap();
        third.insert("a".into(), Tensor::zeros(4, DType::F32, &Device::Cpu).unwrap());
        candle_core::safetensors::save(&third, &path).unwrap();
        let err = read_model_weights(dir.path(), &Device::Cpu).unwrap_err();
        match &err {
            ModelError::DuplicateTensor { name, first, second, .. } => {
                assert_eq!(name, "a");
                assert_eq!([first, second], [&shard_file_name(1, 3), &shard_file_name(3, 3)]);
            }
            other => panic!("unexpected {other}"),
        }
    }

    #[test]
    fn a_tensor_missing_from_its_shard_is_named() {
        let dir = sharded();
        let mut index = index_of(dir.path());
        index["weight_map"]["c"] = shard_file_name(1, 3).into();
        set_index(dir.path(), &index);
        let err = read_model_weights(dir.path(), &Device::Cpu).unwrap_err();
        assert!(
            matches!(&err, ModelError::TensorNotInShard { name, shard, .. }
                if name == "c" && *shard == shard_file_name(1, 3)),
            "{err}"
        );

        let dir = sharded();
        let mut index = index_of(dir.path());
        index["weight_map"].as_object_mut().unwrap().remove("d");
        set_index(dir.path(), &index);
        let err = read_model_weights(dir.path(), &Device::Cpu).unwrap_err();
        assert!(matches!(err, ModelError::BadShardIndex { .. }), "{err}");
        assert!(err.to_string().contains("\"d\""), "{err}");
    }

    #[test]
    fn a_folder_without_weights_is_an_io_error() {
        let dir = tempfile::tempdir().unwrap();
        let err = read_model_weights(dir.path(), &Device::Cpu).unwrap_err();
        assert!(matches!(err, ModelError::Io { .. }), "{err}");
    }
}
