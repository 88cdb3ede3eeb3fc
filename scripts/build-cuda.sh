#!/usr/bin/env bash
# Builds meshstream and meshstream-train with `--features cuda` into target/cuda/release.
#
#   scripts/build-cuda.sh            # then: target/cuda/release/meshstream-train ae --device cuda:0 ...
#   scripts/build-cuda.sh --check    # and check the binaries load and refuse a GPU they lack
#
# With a system CUDA toolkit, point CUDA_HOME at it (CUDA_HOME=/usr/local/cuda). Without one,
# as on our build machines, the toolkit is made from NVIDIA's PyPI wheels by
# scripts/cuda-toolkit.sh (about 700 MB downloaded once, into target/cuda-toolkit).
# CUDA_COMPUTE_CAP is the GPU architecture the kernels are built for (default 90: H100, H200);
# candle asks nvidia-smi when it is unset, which fails on a machine without a GPU.
# The binaries need the driver's libcuda.so.1 and the toolkit's libcudart, libcublas and
# libcurand at run time (on a GPU machine without a toolkit: PyTorch's nvidia/cu13/lib).
set -euo pipefail
cd "$(dirname "$0")/.."
check=false
if [[ ${1:-} == --check ]]; then
    check=true
    shift
fi
if [[ -z ${CUDA_HOME:-} ]]; then
    CUDA_HOME=$(scripts/cuda-toolkit.sh)
fi
export CUDA_HOME CUDA_COMPUTE_CAP=${CUDA_COMPUTE_CAP:-90}
export PATH=$CUDA_HOME/bin:$PATH
# The linker's search path: the wheels' toolkit keeps everything in lib (the driver stand-in
# too); a system toolkit keeps its libraries in lib64 and the driver's stub in lib64/stubs.
for dir in "$CUDA_HOME/lib" "$CUDA_HOME/lib64" "$CUDA_HOME/lib64/stubs"; do
    [[ -d $dir ]] && LIBRARY_PATH=$dir${LIBRARY_PATH:+:$LIBRARY_PATH}
done
export LIBRARY_PATH
target=${CARGO_TARGET_DIR:-target/cuda}
cargo build --release --locked --features cuda --target-dir "$target" --bins "$@"
echo "built $target/release/meshstream and $target/release/meshstream-train" >&2
$check || exit 0

# Without a GPU the loader still needs a libcuda.so.1: the link-time stand-in (or the system
# toolkit's stub) serves, and every CUDA call then fails as it would without a device.
probe=$(mktemp -d)
trap 'rm -rf "$probe"' EXIT
for stub in "$CUDA_HOME/stub/libcuda.so" "$CUDA_HOME/lib64/stubs/libcuda.so"; do
    [[ -f $stub ]] && ln -sf "$stub" "$probe/libcuda.so.1"
done
export LD_LIBRARY_PATH=$probe:$CUDA_HOME/lib:$CUDA_HOME/lib64${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
train=$target/release/meshstream-train
if ldd "$train" | grep 'not found'; then
    echo "build-cuda check: $train lacks the libraries above" >&2
    exit 1
fi
"$train" check-device --model models/default --device cpu --meshes 2
if "$train" check-device --model models/default --device cuda:0 --meshes 2 2>"$probe/err"; then
    echo "build-cuda check: cuda:0 answered on a machine without a GPU?" >&2
else
    echo "build-cuda check: without a GPU, cuda:0 is refused: $(head -1 "$probe/err")" >&2
fi
echo "build-cuda check: passed" >&2
