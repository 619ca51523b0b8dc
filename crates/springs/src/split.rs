//! Running the slabs of a split rollout ([`crate::SimConfig::partitions`]) on several cores.
//!
//! A substep has three slab phases (elastic pass, forward sweep, backward sweep), each only
//! tens of microseconds long. Rayon's fork-join hands a phase to a sleeping worker too slowly
//! for that (on the dev VM the second half was always finished by the first thread before the
//! other woke up), so a split step runs its own "crew": helper threads spawned for the step that
//! spin on an atomic phase counter, each working on a fixed set of slabs. The calling thread
//! runs the serial parts (cross springs, kick, ground, grippers, effects) and its own slabs.
//! Which thread runs a slab never changes what the slab computes, so results are the same for
//! any crew size, including none (every slab on the calling thread).
//!
//! The crew has as many threads as rayon's current thread count allows (`RAYON_NUM_THREADS`, or
//! the pool installed around the call), at most one per slab. Inside [`crate::rollout_batch`]
//! the cores are already busy with other rollouts, so there every slab runs on the job's thread;
//! code that runs split rollouts inside its own parallel loops should do the same by leaving
//! `partitions` at 1.

use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Mutex, PoisonError, RwLock};

use glam::Vec3A;

use crate::partition::{Partition, SlabBuffers};
use crate::step::Scratch;
use crate::{Backbone, kernels};

/// One slab phase of a substep.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    Elastic = 1,
    Forward = 2,
    Backward = 3,
    Exit = 0,
}

/// The shared arrays a phase reads: moved in from the scratch before the phase, back after.
#[derive(Default)]
struct Globals {
    x: Vec<Vec3A>,
    v: Vec<Vec3A>,
    rest: Vec<f32>,
}

/// Helper threads of one split step or rollout and what they share with the calling thread.
pub(crate) struct Crew {
    /// `(sequence << 2) | phase`, bumped by the calling thread to start a phase.
    command: AtomicU32,
    /// Helpers that finished the current phase.
    done: AtomicU32,
    failed: AtomicBool,
    globals: RwLock<Globals>,
    slabs: Vec<Mutex<SlabBuffers>>,
    /// Threads including the calling one.
    threads: usize,
}

thread_local! {
    /// Set while this thread runs one job of [`crate::rollout_batch`].
    static IN_BATCH: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Run `f` as one job of a batch: split rollouts inside it run their slabs on this thread.
pub(crate) fn as_batch_job<R>(f: impl FnOnce() -> R) -> R {
    let before = IN_BATCH.with(|b| b.replace(true));
    let out = f();
    IN_BATCH.with(|b| b.set(before));
    out
}

/// Number of threads a split rollout of `backbone` uses from the current thread: rayon's
/// current thread count (`RAYON_NUM_THREADS`, or the pool installed around the call), at most
/// one per slab, and one inside [`crate::rollout_batch`].
pub(crate) fn crew_size(backbone: &Backbone) -> usize {
    match &backbone.partition {
        Some(p) if !IN_BATCH.with(std::cell::Cell::get) => {
            rayon::current_num_threads().min(p.members.len()).max(1)
        }
        _ => 1,
    }
}

/// Run `body` with a crew of `threads` threads (the caller plus `threads - 1` helpers) working on
/// the scratch's slabs; with one thread, `body` gets no crew and runs every slab itself.
pub(crate) fn with_crew<R>(
    backbone: &Backbone,
    threads: usize,
    sc: &mut Scratch,
    body: impl FnOnce(&mut Scratch, Option<&Crew>) -> R,
) -> R {
    let Some(p) = backbone.partition.as_ref().filter(|_| threads > 1) else {
        return body(sc, None);
    };
    let crew = Crew {
        command: AtomicU32::new(0),
        done: AtomicU32::new(0),
        failed: AtomicBool::new(false),
        globals: RwLock::new(Globals::default()),
        slabs: std::mem::take(&mut sc.slabs)
            .into_iter()
            .map(Mutex::new)
            .collect(),
        threads,
    };
    let out = std::thread::scope(|s| {
        for t in 1..threads {
            let crew = &crew;
            s.spawn(move || crew.helper(backbone, p, t));
        }
        // Tell the helpers to leave however `body` ends (error return or panic), so that the
        // scope can join them.
        let _exit = ExitOnDrop(&crew);
        body(sc, Some(&crew))
    });
    sc.slabs = crew
        .slabs
        .into_iter()
        .map(|m| m.into_inner().unwrap_or_else(PoisonError::into_inner))
        .collect();
    out
}

struct ExitOnDrop<'a>(&'a Crew);

impl Drop for ExitOnDrop<'_> {
    fn drop(&mut self) {
        let c = self.0.command.load(Ordering::Relaxed);
        self.0
            .command
            .store(((c >> 2) + 1) << 2 | Phase::Exit as u32, Ordering::Release);
    }
}

struct FailOnPanic<'a>(&'a AtomicBool);

impl Drop for FailOnPanic<'_> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.0.store(true, Ordering::Release);
        }
    }
}

/// Spin (then yield, so that a loaded machine still makes progress) until `ready()`.
fn wait(mut ready: impl FnMut() -> bool) {
    let mut spins = 0u32;
    while !ready() {
        if spins < 1 << 9 {
            std::hint::spin_loop();
            spins += 1;
        } else {
            std::thread::yield_now();
        }
    }
}

impl Crew {
    fn helper(&self, bb: &Backbone, p: &Partition, me: usize) {
        let _fail = FailOnPanic(&self.failed);
        let mut seen = 0;
        loop {
            let mut cmd = 0;
            wait(|| {
                cmd = self.command.load(Ordering::Acquire);
                cmd != seen
            });
            seen = cmd;
            let phase = match cmd & 3 {
                1 => Phase::Elastic,
                2 => Phase::Forward,
                3 => Phase::Backward,
                _ => return,
            };
            {
                let g = self.globals.read().unwrap_or_else(PoisonError::into_inner);
                self.run_slabs(bb, p, me, phase, &g);
            }
            self.done.fetch_add(1, Ordering::AcqRel);
        }
    }

    fn run_slabs(&self, bb: &Backbone, p: &Partition, me: usize, phase: Phase, g: &Globals) {
        for k in (me..p.members.len()).step_by(self.threads) {
            let mut buf = self.slabs[k].lock().unwrap_or_else(PoisonError::into_inner);
            slab_phase(bb, p, k, phase, &g.x, &g.v, &g.rest, &mut buf);
        }
    }

    /// Run `phase` on every slab: the helpers' slabs on their threads, the rest here.
    fn phase(&self, bb: &Backbone, p: &Partition, sc: &mut Scratch, phase: Phase) {
        {
            let mut g = self.globals.write().unwrap_or_else(PoisonError::into_inner);
            g.x = std::mem::take(&mut sc.x);
            g.v = std::mem::take(&mut sc.v);
            g.rest = std::mem::take(&mut sc.rest);
        }
        self.done.store(0, Ordering::Release);
        let c = self.command.load(Ordering::Relaxed);
        self.command
            .store(((c >> 2) + 1) << 2 | phase as u32, Ordering::Release);
        {
            let g = self.globals.read().unwrap_or_else(PoisonError::into_inner);
            self.run_slabs(bb, p, 0, phase, &g);
        }
        let helpers = (self.threads - 1) as u32;
        wait(|| {
            assert!(
                !self.failed.load(Ordering::Acquire),
                "a split-rollout helper thread panicked"
            );
            self.done.load(Ordering::Acquire) == helpers
        });
        let mut g = self.globals.write().unwrap_or_else(PoisonError::into_inner);
        sc.x = std::mem::take(&mut g.x);
        sc.v = std::mem::take(&mut g.v);
        sc.rest = std::mem::take(&mut g.rest);
    }
}

/// What slab `k` does in `phase`, on its private buffers: gather the particles it reads, then
/// its springs' elastic pass or one dashpot sweep.
#[allow(clippy::too_many_arguments)]
fn slab_phase(
    bb: &Backbone,
    p: &Partition,
    k: usize,
    phase: Phase,
    x: &[Vec3A],
    v: &[Vec3A],
    rest: &[f32],
    buf: &mut SlabBuffers,
) {
    let members = &p.members[k];
    let r = p.ranges[k].clone();
    match phase {
        Phase::Elastic => {
            for (j, &g) in members.iter().enumerate() {
                buf.x[j] = x[g as usize];
                buf.f[j] = Vec3A::ZERO;
            }
            if bb.explicit_damping {
                for (j, &g) in members.iter().enumerate() {
                    buf.v[j] = v[g as usize];
                }
            }
            let springs = &p.local_springs[r.clone()];
            bb.elastic_pass(
                r.start,
                springs,
                &buf.x,
                &buf.v,
                rest,
                &mut buf.f,
                &mut buf.dir,
            );
        }
        Phase::Forward | Phase::Backward => {
            for (j, &g) in members.iter().enumerate() {
                buf.v[j] = v[g as usize];
            }
            if phase == Phase::Forward {
                kernels::damping_forward(&buf.damp, &buf.dir, &mut buf.v);
            } else {
                kernels::damping_backward(&buf.damp, &buf.dir, &mut buf.v);
            }
        }
        Phase::Exit => {}
    }
}

/// Run `phase` on every slab, with the crew or on this thread.
fn all_slabs(bb: &Backbone, p: &Partition, sc: &mut Scratch, crew: Option<&Crew>, phase: Phase) {
    match crew {
        Some(c) => c.phase(bb, p, sc, phase),
        None => {
            let Scratch {
                x, v, rest, slabs, ..
            } = sc;
            for (k, buf) in slabs.iter_mut().enumerate() {
                slab_phase(bb, p, k, phase, x, v, rest, buf);
            }
        }
    }
}

/// Borrow slab `k`'s buffers, wherever they are at the moment.
fn with_slab<R>(
    sc: &Scratch,
    crew: Option<&Crew>,
    k: usize,
    f: impl FnOnce(&SlabBuffers) -> R,
) -> R {
    match crew {
        Some(c) => f(&c.slabs[k].lock().unwrap_or_else(PoisonError::into_inner)),
        None => f(&sc.slabs[k]),
    }
}

/// The elastic pass of a split rollout: every slab on a private copy of its particles, their
/// forces added to the shared array slab by slab, then the cross springs.
pub(crate) fn elastic(bb: &Backbone, p: &Partition, sc: &mut Scratch, crew: Option<&Crew>) {
    all_slabs(bb, p, sc, crew, Phase::Elastic);
    for (k, members) in p.members.iter().enumerate() {
        let f = &mut sc.f;
        let mut add = |buf: &SlabBuffers| {
            for (j, &g) in members.iter().enumerate() {
                f[g as usize] += buf.f[j];
            }
        };
        match crew {
            Some(c) => add(&c.slabs[k].lock().unwrap_or_else(PoisonError::into_inner)),
            None => add(&sc.slabs[k]),
        }
    }
    let c = p.cross_start;
    bb.elastic_pass(
        c,
        &bb.springs[c..],
        &sc.x,
        &sc.v,
        &sc.rest,
        &mut sc.f,
        &mut sc.dir[c..],
    );
}

/// The dashpot sweeps of a split rollout, in the palindromic order `slabs, cross, cross
/// reversed, slabs reversed` (slabs commute: they share no particle), so the pair of sweeps is
/// still a symmetric contraction (docs/physics.md).
pub(crate) fn damping(bb: &Backbone, p: &Partition, sc: &mut Scratch, crew: Option<&Crew>) {
    all_slabs(bb, p, sc, crew, Phase::Forward);
    scatter_velocities(p, sc, crew);
    let c = p.cross_start;
    kernels::damping_sweeps(&sc.damp[c..], &sc.dir[c..], &mut sc.v);
    all_slabs(bb, p, sc, crew, Phase::Backward);
    scatter_velocities(p, sc, crew);
}

fn scatter_velocities(p: &Partition, sc: &mut Scratch, crew: Option<&Crew>) {
    for (k, members) in p.members.iter().enumerate() {
        let mut out = std::mem::take(&mut sc.v);
        with_slab(sc, crew, k, |buf| {
            for (j, &g) in members.iter().enumerate() {
                out[g as usize] = buf.v[j];
            }
        });
        sc.v = out;
    }
}

/// Fill every slab's dashpot sweep data: local endpoints, weights from the springs' impulse
/// weights and the current inverse masses.
pub(crate) fn fill_damp(bb: &Backbone, p: &Partition, sc: &mut Scratch, crew: Option<&Crew>) {
    let Scratch {
        slabs, inv_m_eff, ..
    } = sc;
    for (k, r) in p.ranges.iter().enumerate() {
        let mut guard;
        let buf = match crew {
            Some(c) => {
                guard = c.slabs[k].lock().unwrap_or_else(PoisonError::into_inner);
                &mut *guard
            }
            None => &mut slabs[k],
        };
        for (j, d) in buf.damp.iter_mut().enumerate() {
            let s = r.start + j;
            let ([a, b], [la, lb]) = (bb.springs[s], p.local_springs[s]);
            *d = kernels::DampSpring {
                a: la,
                b: lb,
                wa: bb.damp_weight[s] * inv_m_eff[a as usize],
                wb: bb.damp_weight[s] * inv_m_eff[b as usize],
            };
        }
    }
}
