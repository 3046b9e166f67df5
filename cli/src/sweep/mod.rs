//! The parts of `dray sweep` (the command itself is `crate::sweep_cmd`).

pub mod metrics;
pub mod pareto;
pub mod plan;
pub mod report;
pub mod spread;
