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
    /// Every rank's `mine`, on every rank in rank order. Every rank must call it.
    fn all_gather(&self, mine: &[u8]) -> Vec<Vec<u8>>;
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

    fn all_gather(&self, mine: &[u8]) -> Vec<Vec<u8>> {
        vec![mine.to_vec()]
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

/// How an all-reduce of a gradient travels between the ranks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reduction {
    /// Every value: MPI's all-reduce (a ring of N ranks sends 2(N − 1)/N × 4 bytes a value from each).
    Dense,
    /// Only the non-zero values: each rank sends a bitmask of the non-zero entries (1 bit each) and their
    /// values (4 bytes each) to every other rank, and each rank sums every rank's values in rank order.
    Sparse,
}

impl Reduction {
    /// `NERFJIT_ALL_REDUCE`: `dense` (the default), `sparse`, or `auto` (`None`), where each step takes the
    /// one that sends fewer bytes ([`Reduction::cheaper`]). Dense is the default because on the machine it
    /// was measured on (two ranks sharing memory) sparse steps sent 19–27% fewer bytes but took no less time.
    pub fn from_env() -> Result<Option<Reduction>, String> {
        match std::env::var("NERFJIT_ALL_REDUCE").as_deref() {
            Ok("auto") => Ok(None),
            Err(_) | Ok("dense") => Ok(Some(Reduction::Dense)),
            Ok("sparse") => Ok(Some(Reduction::Sparse)),
            Ok(other) => Err(format!(
                "NERFJIT_ALL_REDUCE is '{other}': use auto, dense or sparse"
            )),
        }
    }

    /// The bytes each of `ranks` ranks sends to reduce `n` values of which the ranks hold `nonzero` non-zero
    /// ones in all (summed over the ranks).
    pub fn bytes_sent(self, n: usize, nonzero: usize, ranks: usize) -> f64 {
        let ranks = ranks.max(1) as f64;
        match self {
            Reduction::Dense => 2.0 * (ranks - 1.0) / ranks * 4.0 * n as f64,
            // Its own bitmask and values, to each of the others.
            Reduction::Sparse => (ranks - 1.0) * (n as f64 / 8.0 + 4.0 * nonzero as f64 / ranks),
        }
    }

    /// The reduction that sends fewer bytes.
    pub fn cheaper(n: usize, nonzero: usize, ranks: usize) -> Reduction {
        let sparse = Reduction::Sparse.bytes_sent(n, nonzero, ranks);
        match sparse < Reduction::Dense.bytes_sent(n, nonzero, ranks) {
            true => Reduction::Sparse,
            false => Reduction::Dense,
        }
    }
}

/// Replaces `values` by their sums over the ranks of `cluster`, sending only the non-zero values
/// ([`Reduction::Sparse`]); every rank gets the same sums, bit for bit.
pub fn all_reduce_sparse_sum(cluster: &dyn Cluster, values: &mut [f32]) {
    let n = values.len();
    let mask_bytes = n.div_ceil(8);
    // The bitmask (value i in bit i % 8 of byte i / 8), then the non-zero values in order.
    let mut mine = vec![0u8; mask_bytes];
    let mut nonzero = Vec::with_capacity(4 * n / 2);
    for (byte, eight) in mine.iter_mut().zip(values.chunks(8)) {
        for (bit, v) in eight.iter().enumerate() {
            if *v != 0.0 {
                *byte |= 1 << bit;
                nonzero.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    mine.extend(nonzero);
    values.fill(0.0);
    for theirs in cluster.all_gather(&mine) {
        let (mask, floats) = theirs.split_at(mask_bytes.min(theirs.len()));
        let mut next = floats.chunks_exact(4);
        for (&byte, eight) in mask.iter().zip(values.chunks_mut(8)) {
            if byte == 0 {
                continue;
            }
            for (bit, v) in eight.iter_mut().enumerate() {
                if byte >> bit & 1 == 1 {
                    if let Some(b) = next.next() {
                        *v += f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                    }
                }
            }
        }
    }
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

    /// Rank 0 of a job whose other ranks' all-gather messages are given; it keeps what it sent.
    struct Others {
        theirs: Vec<Vec<u8>>,
        sent: std::sync::Mutex<Vec<u8>>,
    }

    impl Cluster for Others {
        fn rank(&self) -> usize {
            0
        }
        fn size(&self) -> usize {
            1 + self.theirs.len()
        }
        fn gather(&self, mine: &[u8]) -> Option<Vec<Vec<u8>>> {
            Some(self.all_gather(mine))
        }
        fn all_gather(&self, mine: &[u8]) -> Vec<Vec<u8>> {
            *self.sent.lock().unwrap() = mine.to_vec();
            std::iter::once(mine.to_vec())
                .chain(self.theirs.iter().cloned())
                .collect()
        }
        fn all_reduce_sum(&self, _values: &mut [f32]) {
            unreachable!("the sparse sum gathers")
        }
    }

    /// `values` summed with the other ranks' messages `theirs`, and what this rank sent.
    fn sparse_sum(values: &[f32], theirs: Vec<Vec<u8>>) -> (Vec<f32>, Vec<u8>) {
        let job = Others {
            theirs,
            sent: std::sync::Mutex::new(Vec::new()),
        };
        let mut sum = values.to_vec();
        all_reduce_sparse_sum(&job, &mut sum);
        (sum, job.sent.into_inner().unwrap())
    }

    /// What [`all_reduce_sparse_sum`] sends of `values`.
    fn sparse_message(values: &[f32]) -> Vec<u8> {
        sparse_sum(values, Vec::new()).1
    }

    #[test]
    fn the_sparse_sum_is_the_sum_of_every_ranks_values() {
        // Three ranks' gradients of 21 values, some entries zero on some ranks (or all), and -0.0.
        let ranks: Vec<Vec<f32>> = (0..3)
            .map(|r| {
                (0..21)
                    .map(|i| match (i + r) % 4 {
                        0 => 0.0,
                        1 => -0.0,
                        _ => (i as f32 - 7.5) * 0.25 + r as f32,
                    })
                    .collect()
            })
            .collect();
        let (sum, _) = sparse_sum(&ranks[0], ranks[1..].iter().map(|v| sparse_message(v)).collect());
        let expected: Vec<f32> = (0..21).map(|i| ranks.iter().fold(0.0, |s, r| s + r[i])).collect();
        assert_eq!(f32_bytes(&sum), f32_bytes(&expected));
        // Each message: a bit per value and 4 bytes per non-zero value.
        let nonzero = ranks[1].iter().filter(|v| **v != 0.0).count();
        assert_eq!(sparse_message(&ranks[1]).len(), 21usize.div_ceil(8) + 4 * nonzero);
    }

    #[test]
    fn the_cheaper_reduction_follows_the_bytes() {
        // Two ranks: a dense all-reduce sends 4 bytes a value; a sparse one 1/8 + 4 × the non-zero share.
        assert_eq!(Reduction::Dense.bytes_sent(1000, 2000, 2), 4000.0);
        assert_eq!(Reduction::Sparse.bytes_sent(1000, 1400, 2), 125.0 + 2800.0);
        assert_eq!(Reduction::cheaper(1000, 1400, 2), Reduction::Sparse);
        assert_eq!(Reduction::cheaper(1000, 1990, 2), Reduction::Dense);
        // More ranks: each rank's values go to every other rank, so sparse pays only when few are non-zero.
        assert_eq!(Reduction::cheaper(1000, 8 * 700, 8), Reduction::Dense);
        assert_eq!(Reduction::cheaper(1000, 8 * 100, 8), Reduction::Sparse);
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
