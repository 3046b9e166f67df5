# The dray image: one binary, `dray`, for every role (coordinator, worker, cache, cluster,
# render, submit). Multi-stage: a Rust build stage and a small runtime stage.
#
#   docker build -t dray .
#   docker run --rm -p 50051:50051 dray coordinator --listen 0.0.0.0:50051
#
# Base images are build arguments with the usual defaults, so a machine with no image
# registry can supply local ones (tests/container/run.sh makes them when missing):
#   --build-arg RUST_IMAGE=...     the build stage: Rust 1.95 (rust-version of the
#                                  workspace) on Debian bookworm, with a C++ compiler
#                                  (nv-flip builds NVIDIA's FLIP from C++)
#   --build-arg RUNTIME_IMAGE=...  the runtime stage: Debian bookworm (glibc, libstdc++)
# Offline build from vendored crates: put `cargo vendor` output in vendor/ at the top of
# the build context and build with
#   docker build --network none --build-arg OFFLINE=1 ...
# (the Dockerfile itself needs no network then; vendor/ is not in the repository).
#
# Written for the classic builder as well as BuildKit: no RUN --mount, no heredocs.

ARG RUST_IMAGE=rust:1.95-bookworm
ARG RUNTIME_IMAGE=debian:bookworm-slim

FROM ${RUST_IMAGE} AS build
# Lets a builder without BuildKit find this stage's leftover image (tests/container/run.sh
# removes the previous one after a build).
LABEL io.github.dray.stage=build
# 1: build from vendor/ with no network (cargo --offline, crates.io replaced by vendor/).
ARG OFFLINE=0
WORKDIR /src
COPY . .
RUN set -eu; \
    if [ "$OFFLINE" = 1 ]; then \
      if [ ! -d vendor ]; then \
        echo "OFFLINE=1 needs cargo vendor's output in vendor/ of the build context" >&2; \
        exit 1; \
      fi; \
      set -- --offline \
        --config 'source.crates-io.replace-with="vendored-sources"' \
        --config 'source.vendored-sources.directory="/src/vendor"'; \
    fi; \
    cargo build --release --locked -p dray "$@"; \
    mkdir -p /out; \
    strip --strip-debug -o /out/dray target/release/dray; \
    /out/dray --version

FROM ${RUNTIME_IMAGE} AS runtime
LABEL org.opencontainers.image.title="dray" \
      org.opencontainers.image.description="dray, a distributed ray tracer: coordinator, worker, cache host, cluster, render, submit in one binary" \
      org.opencontainers.image.licenses="MIT OR Apache-2.0"
# An unprivileged user (uid/gid 10001, as helm/dray's securityContext expects), the
# default work directory (--work-dir: job packages, a volume shared with the workers) and
# an empty default scene root.
RUN groupadd --system --gid 10001 dray \
 && useradd --system --uid 10001 --gid dray --home-dir /var/lib/dray --no-create-home \
      --shell /usr/sbin/nologin dray \
 && mkdir -p /var/lib/dray/work /scenes \
 && chown -R dray:dray /var/lib/dray
COPY --from=build /out/dray /usr/local/bin/dray
USER 10001:10001
WORKDIR /var/lib/dray
# Conventional ports (dray has no built-in defaults for them; every command takes
# --listen): 50051 the coordinator's API (dray.v1.RenderService, reflection, health),
# 50052 a worker's ray streams, 50053 the ray-cache host in a worker (--cache-listen) or a
# stand-alone `dray cache`. `dray cluster --base-port P` uses P and P+1...P+N.
EXPOSE 50051 50052 50053
# Health: `dray health` asks the gRPC health service (grpc.health.v1) of the server at
# DRAY_HEALTH_ADDR and exits 0 only when it answers SERVING. The default is the
# coordinator's port; run a worker with -e DRAY_HEALTH_ADDR=127.0.0.1:50052 (a
# stand-alone `dray cache` with 127.0.0.1:50053), and one-shot commands (render, submit)
# with --no-healthcheck. A server on TLS: the check reads the same DRAY_TLS_* variables,
# and DRAY_HEALTH_ADDR must then name the host its certificate was made for.
# (Kubernetes ignores HEALTHCHECK: helm/dray gives its pods gRPC probes instead.)
ENV DRAY_HEALTH_ADDR=127.0.0.1:50051
HEALTHCHECK --interval=10s --timeout=6s --start-period=15s --retries=3 \
  CMD ["dray", "health", "--quiet", "--timeout", "5"]
ENTRYPOINT ["dray"]
CMD ["--help"]
