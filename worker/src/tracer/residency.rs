//! Which domains a step may trace here, and the step's hold on them.

use std::cell::OnceCell;
use std::collections::HashMap;
use std::sync::Arc;

use dray_cache::{MapView, StoreView};
use dray_core::integrator::Integrator;

use super::JobTracer;
use crate::domain_store::LoadedDomain;

/// Which domains a step may trace here: resident, and this worker's to trace under the
/// job's current routing table. Asked once per domain per step.
pub trait Residency {
    /// Domain `d`, if this step may trace it here.
    fn domain(&self, d: u32) -> Option<Arc<LoadedDomain>>;

    /// Whether rays crossing walls go to cache actors (the job has ray caches and the
    /// routing table places their actors).
    fn walls(&self) -> bool {
        false
    }

    /// A view of `wall`'s hit map to consult in place, when the map lives in this
    /// process (sender placement); rays at other walls ask its actor.
    fn map(&self, _wall: u32) -> Option<&MapView> {
        None
    }

    /// A view of `wall`'s ray cache to answer rays in place, when the cache lives in
    /// this process (sender placement).
    fn cache(&self, _wall: u32) -> Option<&StoreView> {
        None
    }
}

/// A fixed set of domains (tests, benchmarks): every one is traced where it is.
impl Residency for HashMap<u32, Arc<LoadedDomain>> {
    fn domain(&self, d: u32) -> Option<Arc<LoadedDomain>> {
        self.get(&d).cloned()
    }
}

/// A step with no domain here (answers applied off the tracing threads): rays go out,
/// to walls when `walls`.
pub struct NoDomains {
    pub walls: bool,
}

impl Residency for NoDomains {
    fn domain(&self, _d: u32) -> Option<Arc<LoadedDomain>> {
        None
    }

    fn walls(&self) -> bool {
        self.walls
    }
}

/// The domains one step has looked up, held until the step ends. Each slot is filled
/// at most once, so a domain looked up here stays put (and borrowable) for the step.
pub(super) struct Pins<'r> {
    residency: &'r dyn Residency,
    slots: Vec<OnceCell<Option<Arc<LoadedDomain>>>>,
    /// [`Residency::walls`], asked once.
    walls: bool,
}

impl<'r> Pins<'r> {
    pub(super) fn new(residency: &'r dyn Residency, domains: usize) -> Self {
        Pins {
            residency,
            slots: (0..domains).map(|_| OnceCell::new()).collect(),
            walls: residency.walls(),
        }
    }

    pub(super) fn walls(&self) -> bool {
        self.walls
    }

    pub(super) fn map(&self, wall: u32) -> Option<&MapView> {
        self.residency.map(wall)
    }

    pub(super) fn cache(&self, wall: u32) -> Option<&StoreView> {
        self.residency.cache(wall)
    }

    pub(super) fn get(&self, d: u32) -> Option<&Arc<LoadedDomain>> {
        self.slots
            .get(d as usize)?
            .get_or_init(|| self.residency.domain(d))
            .as_ref()
    }
}

/// One step's view of the job: the pinned domains and, made once per domain per step,
/// an integrator over each. Making an integrator copies the camera and settings and
/// takes a reference on the domain's light table; once per ray, that meant two atomic
/// counters (the domain's and the table's) shared by every tracing thread, touched
/// twice per ray.
pub(super) struct StepCtx<'p> {
    tracer: &'p JobTracer,
    pub(super) pins: &'p Pins<'p>,
    integrators: Vec<OnceCell<Integrator<'p>>>,
    /// The integrator of steps that touch no triangle (camera rays, rays leaving the
    /// scene).
    pub(super) bare: Integrator<'p>,
}

impl<'p> StepCtx<'p> {
    pub(super) fn new(tracer: &'p JobTracer, pins: &'p Pins<'p>) -> Self {
        StepCtx {
            tracer,
            pins,
            integrators: (0..pins.slots.len()).map(|_| OnceCell::new()).collect(),
            bare: tracer.bare(),
        }
    }

    /// Domain `d` if this step may trace it, with its integrator.
    pub(super) fn domain(&self, d: u32) -> Option<(&'p LoadedDomain, &Integrator<'p>)> {
        let loaded: &'p LoadedDomain = self.pins.get(d)?;
        let integrator = self
            .integrators
            .get(d as usize)?
            .get_or_init(|| self.tracer.integrator(loaded));
        Some((loaded, integrator))
    }
}
