//! dray's gRPC protocol, `dray.v1`, compiled at build time without a system `protoc`.
//!
//! - [`dray::v1`]: messages, clients and servers generated from `proto/dray/v1/*.proto`:
//!   the public `RenderService`, the internal `ClusterService` (registration, heartbeats,
//!   assignments and routing tables, queue reports, contributions) and the worker-to-worker
//!   `RayExchangeService` (bidirectional ray stream), and the coordinator's
//!   `PackageService` (scene package files for workers without a shared volume).
//! - [`FILE_DESCRIPTOR_SET`]: the encoded descriptors (with comments), for gRPC server
//!   reflection: `tonic_reflection::server::Builder::configure()
//!   .register_encoded_file_descriptor_set(dray_proto::FILE_DESCRIPTOR_SET)`.
//! - [`RAY_RECORD_MAX_BYTES`], [`RAY_RECORD_FORMAT`]: the ray record's largest size and
//!   format number; the record itself is an engine type (`dray_core::ray`), not part of this
//!   crate, which needs no engine.
//! - [`worker_name`]: the rule for `RegisterWorkerRequest.name`, checked by the worker
//!   and the coordinator alike.

pub mod reflection;
pub mod worker_name;

/// The most bytes one ray takes in `RayBatch.records` (records are 32 to 64 bytes; the
/// layout is in rays.proto; `dray_core::ray` encodes and decodes it).
pub const RAY_RECORD_MAX_BYTES: usize = 64;

/// The ray record format of this protocol version (`RayStreamOpen.record_format`,
/// `RegisterWorkerRequest.record_format`).
pub const RAY_RECORD_FORMAT: u32 = 2;

/// Generated protobuf code, in its package's module path.
pub mod dray {
    /// Package `dray.v1`.
    pub mod v1 {
        #![allow(clippy::all, missing_docs)]
        tonic::include_proto!("dray.v1");
    }
}

pub use dray::v1;

impl v1::RayCounts {
    /// The counts by kind, in field-number order (`camera` = 1 to `ambient_occlusion` =
    /// 6), which is the engine's ray-kind order: kind `k` is field `k + 1`. This crate
    /// needs no engine; the coordinator's `metrics` tests check the two orders agree
    /// (`dray_core::integrator::RayKind`).
    pub fn by_kind(&self) -> [u64; 6] {
        [
            self.camera,
            self.shadow,
            self.reflection,
            self.refraction,
            self.diffuse,
            self.ambient_occlusion,
        ]
    }

    /// Counts by kind, in [`v1::RayCounts::by_kind`]'s order.
    pub fn from_kinds(k: [u64; 6]) -> v1::RayCounts {
        let [
            camera,
            shadow,
            reflection,
            refraction,
            diffuse,
            ambient_occlusion,
        ] = k;
        v1::RayCounts {
            camera,
            shadow,
            reflection,
            refraction,
            diffuse,
            ambient_occlusion,
        }
    }
}

/// The encoded `google.protobuf.FileDescriptorSet` of `dray.v1` (with its imports and
/// source comments), for gRPC server reflection and for tools that inspect the protocol.
pub const FILE_DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/dray_descriptor.bin"));

/// Fully qualified name of the public render service, for health status and reflection.
pub const RENDER_SERVICE: &str = "dray.v1.RenderService";
/// Fully qualified name of the internal cluster-control service.
pub const CLUSTER_SERVICE: &str = "dray.v1.ClusterService";
/// Fully qualified name of the worker-to-worker ray exchange service.
pub const RAY_EXCHANGE_SERVICE: &str = "dray.v1.RayExchangeService";
/// Fully qualified name of the cache actors' service (ray caches on domain walls).
pub const CACHE_SERVICE: &str = "dray.v1.CacheService";
/// Fully qualified name of the coordinator's scene-package transfer service (workers
/// without a shared volume fetch package files with it).
pub const PACKAGE_SERVICE: &str = "dray.v1.PackageService";
