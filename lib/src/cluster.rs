//! The processes a command runs on: one (the default), or the ranks of an MPI job (`mpirun -np N nerfjit
//! …`, the command line's `mpi` feature). Commands split their frames over the ranks ([`share`]) and gather
//! them on rank 0, which alone prints and writes; the library never links MPI itself: the command line
//! installs its [`Cluster`] once, before any command runs.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::OnceLock;

/// What a command needs of the processes it runs on.
pub trait Cluster: Send + Sync {
    /// This process's rank, from 0.
    fn rank(&self) -> usize;
    /// How many processes run the command.
    fn size(&self) -> usize;
    /// Every rank's `mine`, on rank 0 in rank order; `None` on the other ranks. Every rank must call it.
    fn gather(&self, mine: &[u8]) -> Option<Vec<Vec<u8>>>;
    /// Replaces `values` by their sums over the ranks, on every rank. Every rank must call it.
    fn all_reduce_sum(&self, values: &mut [f32]);
    /// Returns when every rank has called it.
    fn barrier(&self) {
        self.all_reduce_sum(&mut [0.0]);
    }
}

/// One process: rank 0 of 1.
pub struct OneProcess;

impl Cluster for OneProcess {
    fn rank(&self) -> usize {
        0
    }

    fn size(&self) -> usize {
        1
    }

    fn gather(&self, mine: &[u8]) -> Option<Vec<Vec<u8>>> {
        Some(vec![mine.to_vec()])
    }

    fn all_reduce_sum(&self, _values: &mut [f32]) {}
}

static CLUSTER: OnceLock<Box<dyn Cluster>> = OnceLock::new();
/// Whether this process works alone for now ([`alone`]).
static ALONE: AtomicBool = AtomicBool::new(false);

/// Makes `cluster` the processes every command runs on; only the first call counts.
pub fn install(cluster: Box<dyn Cluster>) {
    let _ = CLUSTER.set(cluster);
}

/// The installed cluster ([`OneProcess`] unless the command line installed another, or inside [`alone`]).
pub fn current() -> &'static dyn Cluster {
    if ALONE.load(Ordering::SeqCst) {
        return &OneProcess;
    }
    CLUSTER.get_or_init(|| Box::new(OneProcess)).as_ref()
}

/// The job's cluster even inside [`alone`]: for the work that divides a job's runs among its ranks.
pub fn job() -> &'static dyn Cluster {
    CLUSTER.get_or_init(|| Box::new(OneProcess)).as_ref()
}

/// Runs `work` as if this process were the only one (rank 0 of 1: it prints, writes and trains by itself),
/// as each rank of a sweep runs its own runs.
pub fn alone<T>(work: impl FnOnce() -> T) -> T {
    let before = ALONE.swap(true, Ordering::SeqCst);
    let out = work();
    ALONE.store(before, Ordering::SeqCst);
    out
}

/// `values` as little-endian bytes, to send between ranks.
pub fn f32_bytes<'a>(values: impl IntoIterator<Item = &'a f32>) -> Vec<u8> {
    values.into_iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// The values that [`f32_bytes`] made `bytes` of.
pub fn f32s_of(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

/// The items of `0..n` that rank `rank` of `size` handles: every `size`-th from its rank (so that frames
/// of different cost interleave).
pub fn share(n: usize, rank: usize, size: usize) -> impl Iterator<Item = usize> {
    (rank..n).step_by(size.max(1))
}

/// How many of a batch of `total` items rank `rank` of `size` draws: an equal part, the first `total % size`
/// ranks one more (so that a step of data-parallel training sees the batch the script asks for).
pub fn part(total: usize, rank: usize, size: usize) -> usize {
    let size = size.max(1);
    total / size + usize::from(rank < total % size)
}

/// That every rank of the job draws at least one of a step's `total` items (`what`: the setting's name).
pub fn check_batch(total: usize, what: &str) -> Result<(), String> {
    let size = current().size();
    match total >= size {
        true => Ok(()),
        false => Err(format!(
            "{what} is {total}, fewer than the job's {size} ranks: every rank draws a part of each step's batch"
        )),
    }
}

/// Runs `work` on this rank's share of `0..n` items and gathers every item's bytes on rank 0, in item
/// order; `None` on the other ranks. An error on any rank is an error on rank 0 (the others return theirs).
pub fn split<E: std::fmt::Display>(
    n: usize,
    mut work: impl FnMut(usize) -> Result<Vec<u8>, E>,
) -> Result<Option<Vec<Vec<u8>>>, String> {
    let cluster = current();
    let (rank, size) = (cluster.rank(), cluster.size());
    // Each rank sends its items as [ok flag, index, length, bytes]...: one message.
    let mut mine = Vec::new();
    let mut failed = None;
    for i in share(n, rank, size) {
        match work(i) {
            Ok(bytes) => {
                mine.push(1u8);
                mine.extend((i as u64).to_le_bytes());
                mine.extend((bytes.len() as u64).to_le_bytes());
                mine.extend(bytes);
            }
            Err(e) => {
                failed = Some(format!("rank {rank}: {e}"));
                break;
            }
        }
    }
    if let Some(message) = &failed {
        mine.push(0);
        mine.extend(message.as_bytes());
    }
    let Some(all) = cluster.gather(&mine) else {
        return failed.map_or(Ok(None), Err);
    };
    let mut items: Vec<Option<Vec<u8>>> = vec![None; n];
    for bytes in all {
        let mut at = 0;
        while at < bytes.len() {
            if bytes[at] == 0 {
                return Err(String::from_utf8_lossy(&bytes[at + 1..]).into_owned());
            }
            let word = |k: usize| u64::from_le_bytes(bytes[k..k + 8].try_into().unwrap_or([0; 8])) as usize;
            let (i, len) = (word(at + 1), word(at + 9));
            items[i] = Some(bytes[at + 17..at + 17 + len].to_vec());
            at += 17 + len;
        }
    }
    items
        .into_iter()
        .enumerate()
        .map(|(i, item)| item.ok_or_else(|| format!("item {i} came from no rank")))
        .collect::<Result<Vec<_>, _>>()
        .map(Some)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shares_cover_every_item_once() {
        for size in 1..5 {
            let mut all: Vec<usize> = (0..size).flat_map(|r| share(11, r, size)).collect();
            all.sort();
            assert_eq!(all, (0..11).collect::<Vec<_>>());
        }
    }

    #[test]
    fn parts_add_up_to_the_batch() {
        for size in 1..6 {
            let parts: Vec<usize> = (0..size).map(|r| part(1023, r, size)).collect();
            assert_eq!(parts.iter().sum::<usize>(), 1023);
            assert!(parts.iter().max().unwrap() - parts.iter().min().unwrap() <= 1);
        }
    }

    #[test]
    fn floats_survive_their_bytes() {
        let values = [0.0, -1.5, f32::INFINITY, f32::MIN_POSITIVE, 3.25e7];
        assert_eq!(f32s_of(&f32_bytes(&values)), values);
    }

    #[test]
    fn alone_is_one_process_until_it_returns() {
        assert!(alone(|| current().size() == 1 && current().rank() == 0));
        assert!(!ALONE.load(Ordering::SeqCst));
    }

    #[test]
    fn one_process_gets_every_item_in_order() {
        let items = split(5, |i| Ok::<_, String>(vec![i as u8; i])).unwrap().unwrap();
        assert_eq!(items.len(), 5);
        assert_eq!(items[3], [3, 3, 3]);
        assert_eq!(
            split(3, |i| if i == 1 { Err("bad") } else { Ok(vec![]) }).unwrap_err(),
            "rank 0: bad"
        );
    }
}
