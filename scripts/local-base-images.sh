#!/usr/bin/env bash
# Base images for a machine that has a Docker daemon but no registry to pull from.
#
# The Dockerfiles keep their ordinary FROM lines (debian:bookworm-slim, rust:R-slim-bookworm);
# where those images can be pulled, this script does nothing but pull them. Where they cannot,
# it makes them here:
#   debian:bookworm-slim     debootstrap --variant=minbase bookworm, imported with docker import
#   rust:R-slim-bookworm     that, plus gcc and the host's own Rust toolchain (R: the
#                            Dockerfile's RUST_VERSION), as the official rust image lays it out
#   $PROMETHEUS_IMAGE        Debian's prometheus package (default name meshstream-local/prometheus),
#                            for the compose test: deploy/compose.yaml takes it as PROMETHEUS_IMAGE
# Builds reach Debian's mirror and crates.io through the host's network (--network host); the
# host's own extra CA certificates (/usr/local/share/ca-certificates) go into the local builder
# image only, so that cargo inside it trusts what the host trusts.
#
# Environment: DOCKER (the client, default docker, else Debian's when docker lacks buildx), WORK (scratch folder, default
# target/base-images), MIRROR (default: the host's first Debian mirror, else deb.debian.org).
set -euo pipefail
cd "$(dirname "$0")/.."

DOCKER=${DOCKER:-docker}
# Docker's own client builds with BuildKit only through its buildx plug-in; Debian's docker.io
# client (/usr/bin/docker) has BuildKit built in.
if ! "$DOCKER" buildx version >/dev/null 2>&1 && [[ -x /usr/bin/docker ]]; then
    DOCKER=/usr/bin/docker
fi
WORK=${WORK:-target/base-images}
PROMETHEUS_IMAGE=${PROMETHEUS_IMAGE:-meshstream-local/prometheus:debian}
RUST_VERSION=$(sed -n 's/^ARG RUST_VERSION=//p' Dockerfile | head -n1)
DEBIAN_IMAGE=debian:bookworm-slim
RUST_IMAGE=rust:${RUST_VERSION}-slim-bookworm

have() { "$DOCKER" image inspect "$1" >/dev/null 2>&1; }
# A pull that fails (no registry) fails fast; one that hangs is cut short.
pulled() { timeout 120 "$DOCKER" pull -q "$1" >/dev/null 2>&1; }

mirror() {
    if [[ -n ${MIRROR:-} ]]; then echo "$MIRROR"; return; fi
    local found
    found=$(grep -hE '^(deb|URIs:) ' /etc/apt/sources.list /etc/apt/sources.list.d/* 2>/dev/null |
        grep -oE 'https?://[^ ]+/debian/?( |$)' | head -n1 | tr -d ' ' || true)
    echo "${found:-http://deb.debian.org/debian}"
}

make_debian() {
    local root="$WORK/bookworm-rootfs"
    echo "== $DEBIAN_IMAGE: debootstrap --variant=minbase bookworm ($(mirror))"
    command -v debootstrap >/dev/null || { echo "debootstrap is not installed" >&2; exit 1; }
    rm -rf "$root"
    mkdir -p "$WORK"
    # debootstrap reports any failed extraction, a full disk included, as "file already exists":
    # the free space goes with its log.
    debootstrap --variant=minbase bookworm "$root" "$(mirror)" >"$WORK/debootstrap.log" 2>&1 ||
        { tail -n 20 "$WORK/debootstrap.log" >&2; df -h "$WORK" >&2; exit 1; }
    # What the official slim image also leaves out: apt's caches and lists.
    rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/*
    tar -C "$root" -c . | "$DOCKER" import --change 'CMD ["bash"]' - "$DEBIAN_IMAGE" >/dev/null
    rm -rf "$root"
}

make_rust() {
    local sysroot context="$WORK/rust-context"
    sysroot=$(rustc --print sysroot)
    echo "== $RUST_IMAGE: $DEBIAN_IMAGE + gcc + the host's $(rustc --version)"
    rm -rf "$context"
    mkdir -p "$context/toolchain" "$context/ca"
    # The compiler and standard library; not the documentation (share/).
    cp -a "$sysroot/bin" "$sysroot/lib" "$context/toolchain/"
    [[ -d $sysroot/libexec ]] && cp -a "$sysroot/libexec" "$context/toolchain/"
    cp /usr/local/share/ca-certificates/*.crt "$context/ca/" 2>/dev/null || true
    cat >"$context/Dockerfile" <<EOF
FROM $DEBIAN_IMAGE
RUN apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev ca-certificates \\
    && rm -rf /var/lib/apt/lists/*
COPY ca/ /usr/local/share/ca-certificates/
RUN update-ca-certificates
COPY toolchain/ /usr/local/rust/
ENV RUSTUP_HOME=/usr/local/rustup CARGO_HOME=/usr/local/cargo \\
    PATH=/usr/local/cargo/bin:/usr/local/rust/bin:\$PATH
EOF
    DOCKER_BUILDKIT=1 "$DOCKER" build -q --network host -t "$RUST_IMAGE" "$context" >/dev/null
    rm -rf "$context"
}

make_prometheus() {
    local context="$WORK/prometheus-context"
    echo "== $PROMETHEUS_IMAGE: $DEBIAN_IMAGE + Debian's prometheus package"
    rm -rf "$context"
    mkdir -p "$context"
    cat >"$context/Dockerfile" <<EOF
FROM $DEBIAN_IMAGE
RUN apt-get update && apt-get install -y --no-install-recommends prometheus \\
    && rm -rf /var/lib/apt/lists/* && mkdir -p /prometheus && chown prometheus /prometheus
USER prometheus
ENTRYPOINT ["/usr/bin/prometheus"]
CMD ["--config.file=/etc/prometheus/prometheus.yml", "--storage.tsdb.path=/prometheus"]
EOF
    DOCKER_BUILDKIT=1 "$DOCKER" build -q --network host -t "$PROMETHEUS_IMAGE" "$context" >/dev/null
    rm -rf "$context"
}

for image in "$DEBIAN_IMAGE" "$RUST_IMAGE"; do
    if have "$image" || pulled "$image"; then
        echo "== $image: present"
    elif [[ $image == "$DEBIAN_IMAGE" ]]; then
        make_debian
    else
        make_rust
    fi
done
if [[ ${WITH_PROMETHEUS:-1} == 1 ]]; then
    upstream=$(sed -n 's/.*PROMETHEUS_IMAGE:-\([^}]*\)}.*/\1/p' deploy/compose.yaml | head -n1)
    if have "$PROMETHEUS_IMAGE"; then
        echo "== $PROMETHEUS_IMAGE: present"
    elif pulled "$upstream"; then
        "$DOCKER" tag "$upstream" "$PROMETHEUS_IMAGE"
    else
        make_prometheus
    fi
fi
