//! Checkpoints of a partition's state: a job resumed from its partitions' checkpoints gives the
//! outputs of an uninterrupted one bit for bit; a checkpoint of another job is refused with what
//! to do; a damaged one is a typed error, ignored by the resume.
#![allow(clippy::unwrap_used)]

use std::cell::RefCell;
use std::path::Path;
use std::rc::Rc;
use std::time::{Duration, Instant};

use slag_common::Error;

use super::checkpoint;
use super::gather::Assembled;
use super::handout::Handout;
use super::map::split;
use super::records::{MapStats, ToReducer};
use super::reduce::{Checkpointer, Forms, PartitionReducer, Resume};
use super::resume::read_checkpoint;
use super::tests::{
    ALL_FORMS, contributions, distributed_forms, key, reduce_and_assemble, shuffle,
};
use crate::aggregate::{ContributionStore, ImageContribution, ReduceParams};

/// The mixture and the masks' record (checkpoints do not hold the dense contributions).
const FORMS: Forms = Forms {
    dense: false,
    ..ALL_FORMS
};

/// The digest of the job every test checkpoint belongs to.
const JOB: [u8; 32] = [7; 32];

/// Partition `p` of `peers` starting from `resume`, spilling under `dir`.
fn reducer(p: usize, peers: usize, dir: &Path, resume: Resume) -> PartitionReducer {
    let store = ContributionStore::new(0, dir.join(format!("spill-{p}")));
    let slot = Rc::new(RefCell::new(Some(resume)));
    PartitionReducer::new(
        p as u32,
        peers as u32,
        ReduceParams::default(),
        FORMS,
        store,
        slot,
    )
}

/// Checkpoints of job [`JOB`] to `path` after every view taken in.
fn every_view(path: std::path::PathBuf) -> Resume {
    Resume {
        saved: None,
        checkpoints: Some(Checkpointer {
            path,
            job: JOB,
            every: Duration::ZERO,
            last: Instant::now(),
            written: 0,
            count: 0,
            seconds: 0.0,
            bytes: 0,
        }),
    }
}

/// View `view`'s part of partition `p`.
fn part(images: &[ImageContribution], n: usize, peers: usize, p: usize, view: usize) -> ToReducer {
    let scene = (n as u64, images.len() as u32);
    let parts = split(&images[view], view as u32, peers, scene, false);
    ToReducer::Image(parts.into_iter().nth(p).unwrap())
}

/// Partition `p` takes in views 1, 0, 2, …, `held - 1` (view 1 waits for view 0) and then view
/// `held + 1` (which waits for `held`, never sent), writing a checkpoint after each view; then
/// it is dropped as a killed process would be. Returns the views its checkpoint holds.
fn run_until_killed(
    images: &[ImageContribution],
    n: usize,
    peers: usize,
    p: usize,
    held: usize,
    dir: &Path,
) -> u32 {
    let path = checkpoint::path(dir, p as u32, peers as u32);
    let mut r = reducer(p, peers, dir, every_view(path));
    let mut order: Vec<usize> = (0..held).collect();
    order.swap(0, 1);
    order.push(held + 1);
    for v in order {
        r.absorb(part(images, n, peers, p, v));
    }
    drop(r);
    let saved = read_checkpoint(dir, p as u32, peers as u32, &JOB).unwrap();
    saved.map_or(0, |s| s.progress.next)
}

/// The rerun: each partition resumes from its checkpoint under `dir`; worker 0 hands out the
/// views some partition lacks ([`Handout`]) to workers asking in turn, worker 1 once for every
/// two asks of each of the others (a slow process); each view's parts go only to the partitions that
/// lack it, in a shuffled arrival; worker 0 assembles.
fn rerun(
    images: &[ImageContribution],
    n: usize,
    peers: usize,
    held: &[u32],
    dir: &Path,
) -> Assembled {
    let mut records = Vec::new();
    let mut handout = Handout::new(images.len(), held, peers);
    let mut stats: Vec<MapStats> = (0..peers)
        .map(|w| MapStats {
            worker: w as u32,
            resumed: if w == 0 { handout.skipped() } else { 0 },
            ..Default::default()
        })
        .collect();
    let mut sent = vec![vec![0u64; peers]; peers];
    let asks = [0, 2, 0, 2, 1].into_iter().cycle();
    for w in asks {
        if handout.all_ended() {
            break;
        }
        let Some(i) = handout.grant(w as u32) else {
            continue;
        };
        stats[w].work.images += 1;
        stats[w].views.push(i);
        for p in (0..peers).filter(|&p| held[p] <= i) {
            sent[w][p] += 1;
            records.push(part(images, n, peers, p, i as usize));
        }
    }
    for w in 0..peers {
        for (p, &sent) in sent[w].iter().enumerate() {
            records.push(ToReducer::Done {
                partition: p as u32,
                worker: w as u32,
                images: sent,
                job: Some(key(n, images.len() as u64, images[0].dim)),
                stats: (p == 0).then(|| stats[w].clone()),
            });
        }
    }
    shuffle(&mut records, 99);
    let reducers: Vec<PartitionReducer> = (0..peers)
        .map(|p| {
            let saved = read_checkpoint(dir, p as u32, peers as u32, &JOB).unwrap();
            let resume = Resume {
                saved,
                checkpoints: None,
            };
            reducer(p, peers, dir, resume)
        })
        .collect();
    reduce_and_assemble(reducers, records, n, FORMS, images.len()).unwrap()
}

/// Three partitions killed after 2, 4 and 6 views (views 2 and 3 folded by some partitions and
/// not others, a view waiting behind a missing one in each), resumed: the mixture and the
/// masks' record are bit for bit those of the uninterrupted job, and the report says what was
/// restored and which views no process encoded again.
#[test]
fn partitions_resumed_from_their_checkpoints_give_the_uninterrupted_outputs() {
    let (n, dim, peers) = (2500usize, 6, 3usize);
    let images = contributions(10, n, 7, dim);
    let want = distributed_forms(&images, n, peers, FORMS, |_| {}).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let held: Vec<u32> = (0..peers)
        .map(|p| run_until_killed(&images, n, peers, p, 2 + 2 * p, dir.path()))
        .collect();
    assert_eq!(
        held,
        [2, 4, 6],
        "each checkpoint holds the views before the gap"
    );
    let got = rerun(&images, n, peers, &held, dir.path());
    let (m, w) = (got.mixture.unwrap(), want.mixture.unwrap());
    let bits = |x: &[f32]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    assert_eq!(m.gaussian_ids, w.gaussian_ids);
    assert_eq!((&m.offsets, &m.atoms), (&w.offsets, &w.atoms));
    assert_eq!(bits(&m.weights), bits(&w.weights));
    assert_eq!(bits(&m.codebook), bits(&w.codebook));
    assert_eq!(got.record, want.record);
    let masks: usize = images.iter().map(|c| c.mask_embeddings.len() / dim).sum();
    let entries: usize = images.iter().map(|c| c.entries.len()).sum();
    assert_eq!((got.counts.masks, got.counts.entries), (masks, entries));
    let c = &got.cluster;
    assert_eq!(
        c.views_resumed, 2,
        "views 0 and 1: every partition held them"
    );
    let restored: Vec<u64> = c.partitions.iter().map(|p| p.views_restored).collect();
    assert_eq!(restored, [2, 4, 6]);
    let views: Vec<&[u32]> = c.workers.iter().map(|w| w.views.as_slice()).collect();
    assert_eq!(
        views,
        [&[2, 4, 7, 9][..], &[6][..], &[3, 5, 8][..]],
        "the views some partition lacks, by work done: the slow worker 1 mapped one"
    );
}

/// A partition's checkpoint read back equals what was written and writes the same bytes again;
/// one of another job, partition or process count is refused with [`Error::Format`] saying
/// what to do; a truncated, extended or altered one is an [`Error::Format`] (never a panic),
/// and the resume ignores it.
#[test]
fn a_checkpoint_round_trips_and_one_of_another_job_or_damaged_is_refused() {
    let (n, dim, peers) = (700usize, 4, 2usize);
    let images = contributions(6, n, 5, dim);
    let dir = tempfile::tempdir().unwrap();
    assert_eq!(run_until_killed(&images, n, peers, 0, 3, dir.path()), 3);
    let path = checkpoint::path(dir.path(), 0, peers as u32);
    let bytes = std::fs::read(&path).unwrap();
    let saved = checkpoint::read(&path).unwrap();
    let again = dir.path().join("again.checkpoint");
    assert_eq!(
        checkpoint::write(&again, &saved).unwrap(),
        bytes.len() as u64
    );
    assert_eq!(std::fs::read(&again).unwrap(), bytes);
    assert_eq!(checkpoint::read(&again).unwrap(), saved);
    let fold = saved.fold.as_ref().unwrap();
    assert_eq!((fold.next, fold.den.len()), (3, n.div_ceil(peers)));
    assert!(fold.keeps_codebook && !fold.codebook.is_empty());

    let foreign = read_checkpoint(dir.path(), 0, peers as u32, &[8; 32]).unwrap_err();
    let text = foreign.to_string();
    assert!(matches!(foreign, Error::Format { .. }), "{foreign:?}");
    assert!(
        text.contains("another job") && text.contains("remove"),
        "{text}"
    );
    for (p, peers) in [(1, 2), (0, 3)] {
        assert!(
            saved.check_job(&path, &JOB, p, peers).is_err(),
            "{p} of {peers}"
        );
    }

    let mut damaged: Vec<Vec<u8>> = (0..bytes.len())
        .step_by(13)
        .map(|len| bytes[..len].to_vec())
        .collect();
    damaged.push([bytes.as_slice(), &[0]].concat());
    for at in [3, 40, 70, bytes.len() / 2, bytes.len() - 1] {
        let mut b = bytes.clone();
        b[at] ^= 0x20;
        damaged.push(b);
    }
    for b in damaged {
        std::fs::write(&path, &b).unwrap();
        match checkpoint::read(&path) {
            Err(Error::Format { message, .. }) => assert!(message.contains("damaged"), "{message}"),
            other => panic!("{} bytes of {}: {other:?}", b.len(), bytes.len()),
        }
        assert!(
            read_checkpoint(dir.path(), 0, peers as u32, &JOB)
                .unwrap()
                .is_none()
        );
    }
}
