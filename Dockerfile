# meshstream: the service (HTTP :8080, gRPC :50051) on the CPU, with models/default baked in.
#
#   docker build -t meshstream .
#   docker run --rm -p 8080:8080 -p 50051:50051 --stop-timeout 40 meshstream
#
# Other weights: mount a model folder (config.json + model.safetensors, optionally dit/) over
# /models/default, or elsewhere and point MESHSTREAM_MODEL at it:
#   docker run -v "$PWD/models/mine:/models/mine:ro" -e MESHSTREAM_MODEL=/models/mine ...
# Every `serve` flag is also a MESHSTREAM_* variable (`docker run meshstream help serve`).
# For NVIDIA GPUs: Dockerfile.cuda.

ARG RUST_VERSION=1.95

FROM rust:${RUST_VERSION}-slim-bookworm AS builder
# meshopt compiles meshoptimizer's C++ (the slim image has gcc only).
RUN apt-get update && apt-get install -y --no-install-recommends g++ \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /src
# The binary is stripped, so the release profile's line tables (kept for `perf` on a host) are
# not built here: on 2 cores a cold release build took 366 s without them against 569 s, this
# image's two build steps in CI 350 s against 684 s.
ENV CARGO_PROFILE_RELEASE_DEBUG=false
# Dependencies first, against stub sources: this layer is rebuilt only when Cargo.toml,
# Cargo.lock, build.rs or the proto change, not on every source change.
COPY Cargo.toml Cargo.lock build.rs ./
COPY proto/ proto/
RUN mkdir -p src/bin \
    && echo 'fn main() {}' > src/main.rs \
    && echo 'fn main() {}' > src/bin/meshstream-train.rs \
    && touch src/lib.rs \
    && cargo build --release --locked --bin meshstream \
    && rm -rf src target/release/.fingerprint/meshstream-*
COPY src/ src/
# The viewer page and its examples, embedded in the binary (src/server/ui.rs).
COPY web/ web/
RUN cargo build --release --locked --bin meshstream \
    && strip target/release/meshstream

FROM debian:bookworm-slim AS runtime
ARG VERSION=0.1.0
LABEL org.opencontainers.image.title="meshstream" \
      org.opencontainers.image.description="FACE mesh generation service: point clouds, meshes and images to artist-style triangle meshes, streamed face by face" \
      org.opencontainers.image.version="${VERSION}" \
      org.opencontainers.image.licenses="MIT OR Apache-2.0" \
      org.opencontainers.image.documentation="README.md#containers"
RUN groupadd --system --gid 10001 meshstream \
    && useradd --system --uid 10001 --gid meshstream --no-create-home --home-dir /nonexistent \
       --shell /usr/sbin/nologin meshstream
COPY --from=builder /src/target/release/meshstream /usr/local/bin/meshstream
# What inference reads; the model card travels with the weights.
COPY models/default/config.json models/default/model.safetensors models/default/MODEL_CARD.md /models/default/
COPY models/default/dit/config.json models/default/dit/model.safetensors /models/default/dit/
ENV MESHSTREAM_MODEL=/models/default \
    MESHSTREAM_HTTP_ADDR=0.0.0.0:8080 \
    MESHSTREAM_GRPC_ADDR=0.0.0.0:50051 \
    MESHSTREAM_LOG_FORMAT=json \
    MESHSTREAM_SHUTDOWN_GRACE=30
USER 10001:10001
EXPOSE 8080 50051
# `serve` finishes accepted requests for MESHSTREAM_SHUTDOWN_GRACE seconds after SIGTERM, then
# closes what is left 2 s later: give it that before SIGKILL (docker run --stop-timeout 40,
# compose stop_grace_period, Kubernetes terminationGracePeriodSeconds).
STOPSIGNAL SIGTERM
HEALTHCHECK --interval=10s --timeout=5s --start-period=60s --retries=3 \
    CMD ["meshstream", "healthcheck"]
ENTRYPOINT ["meshstream"]
CMD ["serve"]
