//! The sampler's write pipeline ([`Sampler`] streams chunks into a sink while later chunks are
//! generated): the rows do not depend on the pool it runs in, a failing sink stops it with the
//! sink's error, and progress reaches the row count.

mod common;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use ism_sample::seed::CHUNK;
use ism_sample::{Collect, Header, Region, SampleBlock, SampleError, Sampler, Sink};

/// More chunks than a 3-thread pool keeps in flight (4 per thread), and a short last chunk.
const COUNT: u64 = 29 * CHUNK as u64 + 123;

fn rows(sampler: &Sampler, surface: bool) -> Collect {
    let mut out = Collect::default();
    if surface {
        sampler.surface(COUNT, &mut out).unwrap();
    } else {
        sampler.volume(COUNT, Region::Complex, &mut out).unwrap();
    }
    out
}

fn bits(c: &Collect) -> (Vec<u64>, Vec<i32>) {
    (
        c.rows.positions.iter().map(|x| x.to_bits()).collect(),
        c.rows.simplices.clone(),
    )
}

/// Pools of 1, 2 and 3 threads and a caller outside any pool (the global pool then generates
/// while the caller writes) give the same rows; and a shorter run's rows are the full run's
/// first ones (each chunk draws from its own stream, whatever is generated before or beside it).
#[test]
fn rows_do_not_depend_on_the_pool() {
    let model = common::curved_models().swap_remove(6).1;
    for surface in [true, false] {
        let make = || {
            Sampler::new(&model)
                .unwrap()
                .seed(5)
                .expected_surface_samples(COUNT)
        };
        let reference = {
            let sampler = make();
            std::thread::spawn(move || bits(&rows(&sampler, surface)))
                .join()
                .unwrap()
        };
        assert_eq!(reference.1.len() as u64, COUNT);
        for threads in [1, 2, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let got = pool.install(|| bits(&rows(&make(), surface)));
            assert!(got == reference, "surface {surface}, {threads} threads");
        }
        // A prefix run: the first 11 chunks and a part, the same rows as the full run's.
        let prefix = 11 * CHUNK as u64 + 7;
        let mut out = Collect::default();
        let sampler = make();
        if surface {
            sampler.surface(prefix, &mut out).unwrap();
        } else {
            sampler.volume(prefix, Region::Complex, &mut out).unwrap();
        }
        let (p, s) = bits(&out);
        assert_eq!(p[..], reference.0[..p.len()]);
        assert_eq!(s[..], reference.1[..s.len()]);
    }
}

/// Takes blocks until the `fail_at`-th, which it refuses.
struct Failing {
    blocks: usize,
    fail_at: usize,
}

impl Sink for Failing {
    fn begin(&mut self, _: &Header) -> ism_sample::Result<()> {
        Ok(())
    }
    fn block(&mut self, _: &SampleBlock) -> ism_sample::Result<()> {
        self.blocks += 1;
        if self.blocks == self.fail_at {
            return Err(SampleError::InvalidArgument("sink full".into()));
        }
        Ok(())
    }
    fn finish(&mut self) -> ism_sample::Result<()> {
        panic!("finish after a failed block");
    }
}

/// A sink error stops the run with that error (no further block, no `finish`, no hang), in any
/// pool; progress is monotonic and ends at the row count.
#[test]
fn sink_errors_stop_the_run_and_progress_counts_rows() {
    let model = common::curved_models().swap_remove(6).1;
    for threads in [1, 2, 3] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let sampler = Sampler::new(&model).unwrap().seed(1);
            for fail_at in [1, 2, 13] {
                let mut sink = Failing { blocks: 0, fail_at };
                let err = sampler
                    .volume(COUNT, Region::Complex, &mut sink)
                    .unwrap_err();
                assert!(err.to_string().contains("sink full"), "{err}");
                assert_eq!(sink.blocks, fail_at);
            }
            let seen = Arc::new(AtomicU64::new(0));
            let last = seen.clone();
            let sampler = sampler.progress(move |done| {
                assert!(done >= last.load(Ordering::SeqCst));
                last.store(done, Ordering::SeqCst);
            });
            let mut out = Collect::default();
            sampler.volume(COUNT, Region::Complex, &mut out).unwrap();
            assert_eq!(seen.load(Ordering::SeqCst), COUNT);
        });
    }
}
