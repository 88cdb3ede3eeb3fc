#!/usr/bin/env bash
# A CUDA 13.0 toolkit folder built from NVIDIA's PyPI wheels, for `--features cuda` builds on a
# machine without a system toolkit (and without a GPU). Prints the folder; use it as
#
#   export CUDA_HOME=$(scripts/cuda-toolkit.sh) CUDA_COMPUTE_CAP=90
#   export PATH=$CUDA_HOME/bin:$PATH LIBRARY_PATH=$CUDA_HOME/lib
#   cargo build --release --features cuda
#
# A machine with a system toolkit needs none of this: CUDA_HOME=/usr/local/cuda (and
# CUDA_COMPUTE_CAP when `nvidia-smi` cannot answer, as on a build machine without a GPU).
#
# Usage: scripts/cuda-toolkit.sh [DIR]   (default target/cuda-toolkit; rerunning reuses it)
set -euo pipefail
cd "$(dirname "$0")/.."
dir=$(realpath -m "${1:-target/cuda-toolkit}")
if [[ -f $dir/.complete ]]; then
    echo "$dir"
    exit 0
fi

# The versions a probe built candle 0.11's kernels with (CUDA 13.0, as on the lent GPU's driver).
wheels=(
    nvidia-cuda-nvcc==13.0.88 nvidia-cuda-crt==13.0.88 nvidia-nvvm==13.0.88
    nvidia-cuda-cccl==13.0.85 nvidia-cuda-runtime==13.0.96 nvidia-cuda-nvrtc==13.0.88
    nvidia-curand==10.4.0.35 nvidia-cublas==13.1.0.3
)
rm -rf "$dir"
mkdir -p "$dir"
python3 -m venv "$dir/venv" >&2
"$dir/venv/bin/pip" install --quiet --no-deps "${wheels[@]}" >&2
cu13=$(echo "$dir"/venv/lib/python3*/site-packages/nvidia/cu13)
[[ -d $cu13 ]] || { echo "cuda-toolkit: no nvidia/cu13 in the wheels' site-packages" >&2; exit 1; }

# Laid out as a toolkit: bin (nvcc), include, nvvm (cicc, libdevice) and lib.
for part in bin include nvvm; do ln -sfn "$cu13/$part" "$dir/$part"; done
mkdir -p "$dir/lib"
# The wheels ship only versioned names (libcublas.so.13); the linker asks for libcublas.so.
for lib in "$cu13"/lib/lib*.so.*; do
    base=$(basename "$lib")
    ln -sfn "$lib" "$dir/lib/$base"
    ln -sfn "$lib" "$dir/lib/${base%%.so.*}.so"
done
ln -sfn lib "$dir/lib64"

# cudarc links the driver dynamically (-lcuda), and no wheel ships libcuda.so: the driver comes
# with the GPU. A stand-in whose every entry point fails satisfies the linker; at run time the
# loader finds the real libcuda.so.1 of the machine's driver (the stand-in is never installed).
syms=$(grep -rhoE '\bcu[A-Z][A-Za-z0-9_]*\b' "$cu13/include/cuda.h" | sort -u)
{
    echo '/* Link-time stand-in for the CUDA driver: every call returns CUDA_ERROR_NO_DEVICE. */'
    for s in $syms; do echo "int $s(void) { return 100; }"; done
} >"$dir/cuda-stub.c"
mkdir -p "$dir/stub"
gcc -shared -fPIC -o "$dir/stub/libcuda.so" "$dir/cuda-stub.c" -Wl,-soname,libcuda.so.1
ln -sfn ../stub/libcuda.so "$dir/lib/libcuda.so"

"$dir/bin/nvcc" --version >&2
touch "$dir/.complete"
echo "$dir"
