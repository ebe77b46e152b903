//! gRPC server reflection for both farm servers: what `grpcurl list` and other generic
//! clients read to call the API without `trove.proto` at hand. Both protocol versions are
//! served (`grpc.reflection.v1`, and `v1alpha`, which older clients still ask for), each
//! describing `trove.v1` and `grpc.health.v1`.

use tonic_reflection::server::v1::{ServerReflection as V1, ServerReflectionServer as V1Server};
use tonic_reflection::server::v1alpha::{ServerReflection as V1Alpha, ServerReflectionServer as V1AlphaServer};
use tonic_reflection::server::Builder;

fn builder() -> Builder<'static> {
    Builder::configure()
        .register_encoded_file_descriptor_set(crate::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
}

/// The reflection services, v1 and v1alpha. A descriptor set that does not decode (which the
/// build would have to have broken; a test here checks it does) leaves a server without
/// reflection, logged, rather than without its API.
pub fn services() -> (Option<V1Server<impl V1>>, Option<V1AlphaServer<impl V1Alpha>>) {
    let v1 = builder().build_v1().map_err(|e| tracing::error!(error = %e, "server reflection (v1) is off")).ok();
    let v1alpha =
        builder().build_v1alpha().map_err(|e| tracing::error!(error = %e, "server reflection (v1alpha) is off")).ok();
    (v1, v1alpha)
}

#[cfg(test)]
mod tests {
    #[test]
    fn both_reflection_services_build_from_the_compiled_descriptors() {
        let (v1, v1alpha) = super::services();
        assert!(v1.is_some() && v1alpha.is_some());
    }
}
