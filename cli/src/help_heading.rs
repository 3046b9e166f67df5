//! The topics `dray render --help` and `dray submit --help` group their flags under, in
//! one place so the two commands (and the flags they share through
//! [`crate::job_flags::JobFlags`]) use the same words. clap lists headings in the order
//! their first flag is declared.

pub const IMAGE: &str = "Image";
pub const INTEGRATOR: &str = "Integrator and effects";
pub const CAMERA: &str = "Camera (docs/cameras.md)";
pub const LIGHTS: &str = "Lights (docs/lights.md)";
pub const NOISE: &str = "Noise and outputs for a denoiser (docs/noise.md)";
pub const OUTPUT: &str = "Output";
pub const CLUSTER: &str = "Workers and scheduling (docs/architecture.md)";
pub const APPROXIMATIONS: &str = "Approximations: ray caches and hit maps (docs/benchmarks.md)";
pub const PERFORMANCE: &str = "Threads and telemetry";
pub const SUBMIT: &str = "Coordinator";
pub const SWEEP: &str = "Sweep";
pub const ANIMATION: &str = "Animation";
