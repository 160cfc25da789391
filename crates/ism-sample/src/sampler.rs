//! The [`Sampler`]: a model evaluator plus a seed, producing point sets into a [`Sink`].
//!
//! Work is split into chunks of [`CHUNK`] samples; each chunk draws from its own ChaCha stream
//! ([`crate::seed`]) and chunks are run in parallel in batches, then handed to the sink in order.
//! Memory stays bounded by one batch, and the output is identical for any thread count.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Condvar, Mutex, OnceLock};
use std::time::Duration;

use ism_format::{IndexedModel, Model};
use ism_geom::{Bary, ModelEval, MAX_VARS};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

use crate::error::{Result, SampleError};
use crate::output::{Column, Header, SampleBlock, Sink};
use crate::seed::{chunk_rng, chunk_sizes, Purpose, CHUNK};
use crate::surface::{SurfaceTable, Weighting};

/// Where volume samples are drawn.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Region {
    /// Uniform in the union `|K|` of the top simplices.
    Complex,
    /// Uniform in an axis-aligned box (first `n` entries of `lo` and `hi`); points outside `|K|`
    /// get simplex −1, label −1 and `F = NaN`.
    Box {
        /// Lower corner.
        lo: [f64; 3],
        /// Upper corner.
        hi: [f64; 3],
    },
}

/// A progress callback: receives the number of rows produced so far.
pub type Progress = Box<dyn Fn(u64) + Send + Sync>;

/// Samples and queries one model. Build with [`Sampler::new`], configure with the builder
/// methods, then call [`Sampler::surface`], [`Sampler::volume`], [`Sampler::near_surface`] or
/// [`Sampler::query`] with any [`Sink`].
pub struct Sampler {
    eval: ModelEval,
    seed: u64,
    weighting: Weighting,
    progress: Option<Progress>,
    /// Surface samples expected in all ([`Sampler::expected_surface_samples`]).
    expected_surface: Option<u64>,
    surface: OnceLock<Result<SurfaceTable>>,
    volumes: OnceLock<Vec<f64>>,
}

impl std::fmt::Debug for Sampler {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sampler")
            .field("seed", &self.seed)
            .field("weighting", &self.weighting)
            .finish_non_exhaustive()
    }
}

impl Sampler {
    /// A sampler of `model` with seed 0. Indexes a copy of the model ([`ModelEval::new`]);
    /// [`Sampler::from_indexed`] shares a checked, indexed model instead (a file read by
    /// `ism_format::io::read_path_indexed`: no copy, no second structural check).
    ///
    /// # Errors
    /// [`SampleError::Geometry`] when the model cannot be evaluated (bad shapes, degenerate
    /// simplices, malformed stage records).
    pub fn new(model: &Model) -> Result<Sampler> {
        let eval = ModelEval::new(model)?;
        Ok(Sampler::from_eval(eval))
    }

    /// A sampler of an indexed model with seed 0, sharing its index ([`ModelEval::from_indexed`]).
    ///
    /// # Errors
    /// [`SampleError::Geometry`] for a degenerate simplex.
    pub fn from_indexed(model: &IndexedModel) -> Result<Sampler> {
        let eval = ModelEval::from_indexed(model)?;
        Ok(Sampler::from_eval(eval))
    }

    /// A sampler over an existing evaluator.
    pub fn from_eval(eval: ModelEval) -> Sampler {
        Sampler {
            eval,
            seed: 0,
            weighting: Weighting::CurvedArea,
            progress: None,
            expected_surface: None,
            surface: OnceLock::new(),
            volumes: OnceLock::new(),
        }
    }

    /// Sets the seed: equal seeds give bit-identical output whatever the thread count.
    pub fn seed(mut self, seed: u64) -> Sampler {
        self.seed = seed;
        self
    }

    /// Calls `progress(rows_so_far)` after each batch of chunks.
    pub fn progress(mut self, progress: impl Fn(u64) + Send + Sync + 'static) -> Sampler {
        self.progress = Some(Box::new(progress));
        self
    }

    /// How many surface (and near-surface) samples will be drawn in all: the surface table then
    /// refines its certified bounds only as far as the candidates it saves on that many samples
    /// pay for the refinement ([`SurfaceTable::with_expected_samples`]). Output for a seed then
    /// depends on this number (not on the thread count). Without it the table uses a fixed
    /// refinement threshold.
    /// The table already built is kept when `count` is the one it was built for (a caller that
    /// keeps its `Sampler` between calls, as the Python package does, pays for it once).
    pub fn expected_surface_samples(mut self, count: u64) -> Sampler {
        if self.expected_surface != Some(count) {
            self.expected_surface = Some(count);
            self.surface = OnceLock::new();
        }
        self
    }

    /// Chooses the surface weighting (tests only: the default is the correct one).
    #[doc(hidden)]
    pub fn weighting(mut self, weighting: Weighting) -> Sampler {
        self.weighting = weighting;
        self.surface = OnceLock::new();
        self
    }

    /// The model evaluator.
    pub fn eval(&self) -> &ModelEval {
        &self.eval
    }

    /// The surface table (built on first use, in parallel).
    ///
    /// # Errors
    /// See [`SurfaceTable::new`].
    pub fn surface_table(&self) -> Result<&SurfaceTable> {
        let t = self.surface.get_or_init(|| {
            SurfaceTable::with_expected_samples(&self.eval, self.weighting, self.expected_surface)
        });
        t.as_ref().map_err(SampleError::duplicate)
    }

    /// Runs `generate` for every chunk and streams the blocks into `sink` in order.
    ///
    /// A pipeline without barriers: [`WINDOW_PER_THREAD`] chunks per thread are in flight as
    /// tasks of the current pool; this thread writes chunk `i` as soon as it is done, spawns
    /// chunk `i + window` in its place, and while it waits for a chunk it runs the pool's pending
    /// chunks itself ([`rayon::yield_now`]). The write is serial (formatting, the system's copy:
    /// a fifth of a 10⁷-sample run in perf, session 19); batches joined one after another left a
    /// thread idle at every join and during each write (1.70× from 1 to 2 threads, session 18).
    /// What each chunk draws depends only on its index (its own stream) and the blocks are
    /// written in index order, so the output is the same whatever the threads.
    fn drive(
        &self,
        header: Header,
        purpose: Purpose,
        sink: &mut dyn Sink,
        generate: impl Fn(&mut ChaCha8Rng, usize, &mut SampleBlock) -> Result<()> + Sync,
    ) -> Result<()> {
        sink.begin(&header)?;
        let sizes: Vec<usize> = chunk_sizes(header.count).collect();
        let window =
            (rayon::current_num_threads() * WINDOW_PER_THREAD).clamp(2, sizes.len().max(2));
        let ring = Ring::new(window);
        let stop = AtomicBool::new(false);
        let make = |i: usize| -> Result<SampleBlock> {
            let mut rng = chunk_rng(self.seed, purpose, i as u64);
            let mut block = SampleBlock::default();
            generate(&mut rng, sizes[i], &mut block)?;
            Ok(block)
        };
        let written = rayon::in_place_scope(|scope| -> Result<()> {
            let spawn = |i: usize| {
                let (ring, stop, make) = (&ring, &stop, &make);
                scope.spawn(move |_| {
                    // After a failure the writer has stopped waiting: skip the chunks still
                    // queued.
                    if !stop.load(Ordering::Relaxed) {
                        ring.put(i, make(i));
                    }
                });
            };
            for i in 0..window.min(sizes.len()) {
                spawn(i);
            }
            let mut done = 0u64;
            for i in 0..sizes.len() {
                let block = ring.take(i);
                if i + window < sizes.len() {
                    spawn(i + window);
                }
                let step = block.and_then(|block| {
                    done += block.len(header.dim) as u64;
                    sink.block(&block)
                });
                if let Err(e) = step {
                    stop.store(true, Ordering::Relaxed);
                    return Err(e);
                }
                if let Some(p) = &self.progress {
                    p(done);
                }
            }
            Ok(())
        });
        written?;
        sink.finish()
    }

    /// The columns of surface samples: position, normal, `F`, source simplex.
    pub fn surface_header(&self, count: u64) -> Header {
        Header {
            dim: self.eval.dim(),
            columns: vec![
                Column::Position,
                Column::Normal,
                Column::Value,
                Column::Simplex,
            ],
            count,
        }
    }

    /// `count` points on the shape, uniform by curved area, with normals, `F` and source simplex.
    ///
    /// # Errors
    /// Table errors ([`SurfaceTable::new`]), numerical failures ([`SurfaceTable::draw`]) and the
    /// sink's errors.
    pub fn surface(&self, count: u64, sink: &mut dyn Sink) -> Result<()> {
        let table = self.surface_table()?;
        let n = self.eval.dim();
        self.drive(
            self.surface_header(count),
            Purpose::Surface,
            sink,
            |rng, size, block| {
                table.draw_each(&self.eval, rng, size, |sp, _| {
                    block.positions.extend_from_slice(&sp.p[..n]);
                    block.normals.extend_from_slice(&sp.normal[..n]);
                    block.values.push(sp.value);
                    block.simplices.push(sp.simplex as i32);
                    Ok(())
                })
            },
        )
    }

    /// The columns of volume and near-surface samples: position, `F`, label, simplex.
    pub fn volume_header(&self, count: u64) -> Header {
        Header {
            dim: self.eval.dim(),
            columns: vec![
                Column::Position,
                Column::Value,
                Column::Label,
                Column::Simplex,
            ],
            count,
        }
    }

    fn cumulative_volumes(&self) -> &[f64] {
        self.volumes.get_or_init(|| {
            let model = self.eval.model();
            let n = model.dim();
            let vols: Vec<f64> = (0..self.eval.num_simplices())
                .into_par_iter()
                .map(|s| {
                    ism_geom::linalg::det(n, &ism_geom::model::edge_matrix(model, model.simplex(s)))
                        .abs()
                })
                .collect();
            let mut acc = 0.0;
            vols.iter()
                .map(|v| {
                    acc += v;
                    acc
                })
                .collect()
        })
    }

    /// Appends one located row (`F`, label, simplex) for point `p`.
    fn push_located(&self, p: &[f64], block: &mut SampleBlock) {
        let n = self.eval.dim();
        block.positions.extend_from_slice(&p[..n]);
        match self.eval.locate(p) {
            Some(l) => {
                let f = self.eval.value_at(l.simplex, &l.w);
                block.values.push(f);
                block.labels.push(i8::from(f < self.eval.model().level));
                block.simplices.push(l.simplex as i32);
            }
            None => {
                block.values.push(f64::NAN);
                block.labels.push(-1);
                block.simplices.push(-1);
            }
        }
    }

    /// `count` points uniform in `region`, with `F`, inside label and simplex.
    ///
    /// # Errors
    /// [`SampleError::InvalidArgument`] for an empty or non-finite box, an empty complex; the sink's
    /// errors.
    pub fn volume(&self, count: u64, region: Region, sink: &mut dyn Sink) -> Result<()> {
        let n = self.eval.dim();
        let level = self.eval.model().level;
        match region {
            Region::Complex => {
                let cum = self.cumulative_volumes();
                let total = *cum
                    .last()
                    .ok_or_else(|| SampleError::InvalidArgument("the complex is empty".into()))?;
                self.drive(
                    self.volume_header(count),
                    Purpose::Volume,
                    sink,
                    |rng, size, block| {
                        for _ in 0..size {
                            let x = rng.random::<f64>() * total;
                            let s = cum.partition_point(|&c| c <= x).min(cum.len() - 1);
                            let w = uniform_barycentric(n, rng);
                            let p = self.eval.point(s, &w);
                            let f = self.eval.value_at(s, &w);
                            block.positions.extend_from_slice(&p[..n]);
                            block.values.push(f);
                            block.labels.push(i8::from(f < level));
                            block.simplices.push(s as i32);
                        }
                        Ok(())
                    },
                )
            }
            Region::Box { lo, hi } => {
                if (0..n).any(|x| !(lo[x].is_finite() && hi[x].is_finite() && lo[x] < hi[x])) {
                    return Err(SampleError::InvalidArgument(format!(
                        "box {:?}..{:?} must be finite with lo < hi on every axis",
                        &lo[..n],
                        &hi[..n]
                    )));
                }
                self.drive(
                    self.volume_header(count),
                    Purpose::Volume,
                    sink,
                    |rng, size, block| {
                        for _ in 0..size {
                            let mut p = [0.0; 3];
                            for x in 0..n {
                                p[x] = lo[x] + (hi[x] - lo[x]) * rng.random::<f64>();
                            }
                            self.push_located(&p, block);
                        }
                        Ok(())
                    },
                )
            }
        }
    }

    /// `count` surface points (uniform by curved area) each displaced by `t·d`, `d` a uniform random
    /// direction and `t ~ N(0, sigma²)`, with `F`, label and simplex at the displaced point.
    ///
    /// # Errors
    /// [`SampleError::InvalidArgument`] for a non-positive or non-finite `sigma`; as
    /// [`Sampler::surface`] otherwise.
    pub fn near_surface(&self, count: u64, sigma: f64, sink: &mut dyn Sink) -> Result<()> {
        if !(sigma.is_finite() && sigma > 0.0) {
            return Err(SampleError::InvalidArgument(format!(
                "sigma must be positive and finite, got {sigma}"
            )));
        }
        let table = self.surface_table()?;
        let n = self.eval.dim();
        self.drive(
            self.volume_header(count),
            Purpose::NearSurface,
            sink,
            |rng, size, block| {
                table.draw_each(&self.eval, rng, size, |sp, rng| {
                    let dir = loop {
                        let mut d = [0.0; 3];
                        for x in d.iter_mut().take(n) {
                            *x = StandardNormal.sample(rng);
                        }
                        let len = d.iter().map(|x| x * x).sum::<f64>().sqrt();
                        if len > 1e-12 {
                            break d.map(|x| x / len);
                        }
                    };
                    let t: f64 =
                        sigma * <StandardNormal as Distribution<f64>>::sample(&StandardNormal, rng);
                    let mut p = sp.p;
                    for x in 0..n {
                        p[x] += t * dir[x];
                    }
                    self.push_located(&p, block);
                    Ok(())
                })
            },
        )
    }

    /// The columns of query results: position, simplex, `F`, sign of `F − c`, `∇F`.
    pub fn query_header(&self, count: u64) -> Header {
        Header {
            dim: self.eval.dim(),
            columns: vec![
                Column::Position,
                Column::Simplex,
                Column::Value,
                Column::Sign,
                Column::Gradient,
            ],
            count,
        }
    }

    /// Evaluates every point (flat, `n` per point): containing simplex (−1 outside `|K|`), `F`,
    /// sign of `F − c` and `∇F` (NaN outside).
    ///
    /// # Errors
    /// [`SampleError::InvalidArgument`] when `points.len()` is not a multiple of `n`; the sink's
    /// errors.
    pub fn query(&self, points: &[f64], sink: &mut dyn Sink) -> Result<()> {
        let n = self.eval.dim();
        if points.len() % n != 0 {
            return Err(SampleError::InvalidArgument(format!(
                "{} coordinates is not a multiple of {n}",
                points.len()
            )));
        }
        let level = self.eval.model().level;
        let header = self.query_header((points.len() / n) as u64);
        sink.begin(&header)?;
        for (i, group) in points.chunks(CHUNK * n * 16).enumerate() {
            let blocks: Vec<SampleBlock> = group
                .par_chunks(CHUNK * n)
                .map(|chunk| {
                    let mut block = SampleBlock::default();
                    for p in chunk.chunks_exact(n) {
                        block.positions.extend_from_slice(p);
                        let located = self.eval.locate(p);
                        match located {
                            Some(l) => {
                                let (f, g) = self.eval.value_and_gradient_at(l.simplex, &l.w);
                                let g = g.unwrap_or([f64::NAN; 3]);
                                block.simplices.push(l.simplex as i32);
                                block.values.push(f);
                                block.signs.push(if f < level {
                                    -1
                                } else if f > level {
                                    1
                                } else {
                                    0
                                });
                                block.gradients.extend_from_slice(&g[..n]);
                            }
                            None => {
                                block.simplices.push(-1);
                                block.values.push(f64::NAN);
                                block.signs.push(0);
                                block.gradients.extend(std::iter::repeat_n(f64::NAN, n));
                            }
                        }
                    }
                    block
                })
                .collect();
            for block in &blocks {
                sink.block(block)?;
            }
            if let Some(p) = &self.progress {
                p(((i + 1) * CHUNK * 16).min(points.len() / n) as u64);
            }
        }
        sink.finish()
    }
}

/// Chunks in flight per pool thread in [`Sampler::drive`]: enough that a thread finishing a chunk
/// always finds another queued while the writer is busy, few enough to keep memory to a few MB.
const WINDOW_PER_THREAD: usize = 4;

/// The blocks in flight of [`Sampler::drive`]: chunk `i` lives in slot `i % len` from its
/// generation until the writer takes it (chunk `i + len` is spawned only after that).
struct Ring {
    slots: Mutex<Vec<Option<Result<SampleBlock>>>>,
    filled: Condvar,
}

impl Ring {
    fn new(len: usize) -> Ring {
        Ring {
            slots: Mutex::new((0..len).map(|_| None).collect()),
            filled: Condvar::new(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Vec<Option<Result<SampleBlock>>>> {
        // A panic while the lock was held leaves only whole slots behind: keep going.
        self.slots.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn put(&self, i: usize, block: Result<SampleBlock>) {
        let mut slots = self.lock();
        let len = slots.len();
        slots[i % len] = Some(block);
        drop(slots);
        self.filled.notify_all();
    }

    /// Chunk `i`, once generated. Meanwhile this thread runs the pool's pending work (the
    /// queued chunks) and sleeps only when there is none: then every chunk still missing is
    /// being generated by another thread, whose `put` wakes it. (The timeout only bounds a
    /// wait on a pool that is not ours, e.g. a caller outside any pool.)
    fn take(&self, i: usize) -> Result<SampleBlock> {
        loop {
            {
                let mut slots = self.lock();
                let len = slots.len();
                if let Some(block) = slots[i % len].take() {
                    return block;
                }
            }
            if rayon::yield_now() == Some(rayon::Yield::Executed) {
                continue;
            }
            let slots = self.lock();
            let len = slots.len();
            if slots[i % len].is_none() {
                let _ = self
                    .filled
                    .wait_timeout(slots, Duration::from_millis(5))
                    .unwrap_or_else(|e| e.into_inner());
            }
        }
    }
}

/// Uniform barycentric coordinates on the `n`-simplex: the spacings of `n` sorted uniforms.
fn uniform_barycentric(n: usize, rng: &mut impl Rng) -> Bary {
    let mut cuts = [0.0f64; MAX_VARS + 1];
    for c in cuts.iter_mut().take(n) {
        *c = rng.random();
    }
    cuts[..n].sort_by(f64::total_cmp);
    let mut w = [0.0; MAX_VARS];
    let mut prev = 0.0;
    for i in 0..n {
        w[i] = cuts[i] - prev;
        prev = cuts[i];
    }
    w[n] = 1.0 - prev;
    w
}
