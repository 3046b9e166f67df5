//! gRPC server reflection for every dray server, so tools discover the API with no
//! `.proto` files. Servers register both protocol versions: `v1`, and `v1alpha`, which
//! many clients still speak only (Python's grpcio-reflection, older grpcurl, grpcui and
//! Postman) and which otherwise answer "server does not support the reflection API".

use tonic_reflection::server::{Builder, Error, v1, v1alpha};

/// The descriptors a dray server offers: `dray.v1` and the standard health service.
fn builder() -> Builder<'static> {
    Builder::configure()
        .register_encoded_file_descriptor_set(crate::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
}

/// The `grpc.reflection.v1` service.
pub fn reflection_v1() -> Result<v1::ServerReflectionServer<impl v1::ServerReflection>, Error> {
    builder().build_v1()
}

/// The `grpc.reflection.v1alpha` service.
pub fn reflection_v1alpha()
-> Result<v1alpha::ServerReflectionServer<impl v1alpha::ServerReflection>, Error> {
    builder().build_v1alpha()
}
