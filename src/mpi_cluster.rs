//! The ranks of an MPI job as the library's [`Cluster`] (the `mpi` feature: rsmpi against the system's
//! Open MPI or MPICH). Without `mpirun` the same binary is one rank of one.

use mpi::collective::SystemOperation;
use mpi::datatype::PartitionMut;
use mpi::environment::Universe;
use mpi::topology::SimpleCommunicator;
use mpi::traits::*;
use nerfjit::cluster::Cluster;

/// MPI's world communicator. MPI is initialized for serialized calls from any thread: only the one thread
/// that runs the command calls it.
struct MpiCluster {
    world: SimpleCommunicator,
    /// This process's rank and the job's size, asked once (so that other threads, such as the signal
    /// handler's, can read them without calling MPI).
    rank: usize,
    size: usize,
}

// SAFETY: MPI is initialized with `Threading::Serialized` and only the command's thread makes MPI calls,
// one at a time.
unsafe impl Send for MpiCluster {}
// SAFETY: as above.
unsafe impl Sync for MpiCluster {}

impl Cluster for MpiCluster {
    fn rank(&self) -> usize {
        self.rank
    }

    fn size(&self) -> usize {
        self.size
    }

    fn gather(&self, mine: &[u8]) -> Option<Vec<Vec<u8>>> {
        let root = self.world.process_at_rank(0);
        // Every rank sends at least a byte: Open MPI refuses the empty buffer of a rank with nothing to send.
        let mine = [&[0u8][..], mine].concat();
        let count = i32::try_from(mine.len()).expect("less than 2 GiB a rank");
        if self.rank != 0 {
            root.gather_into(&count);
            root.gather_varcount_into(&mine[..]);
            return None;
        }
        let mut counts = vec![0i32; self.size()];
        root.gather_into_root(&count, &mut counts[..]);
        Some(receive(&counts, |partition| {
            root.gather_varcount_into_root(&mine[..], partition)
        }))
    }

    fn all_gather(&self, mine: &[u8]) -> Vec<Vec<u8>> {
        // At least a byte from every rank, as in `gather`.
        let mine = [&[0u8][..], mine].concat();
        let count = i32::try_from(mine.len()).expect("less than 2 GiB a rank");
        let mut counts = vec![0i32; self.size];
        self.world.all_gather_into(&count, &mut counts[..]);
        receive(&counts, |partition| {
            self.world.all_gather_varcount_into(&mine[..], partition)
        })
    }

    fn all_reduce_sum(&self, values: &mut [f32]) {
        self.sum(values);
    }

    fn barrier(&self) {
        self.world.barrier();
    }
}

/// The ranks' messages of `counts` bytes each (each with the lead byte every rank sends), received by
/// `collect` into one buffer partitioned by rank, without their lead bytes.
fn receive(counts: &[i32], collect: impl FnOnce(&mut PartitionMut<[u8], &[i32], Vec<i32>>)) -> Vec<Vec<u8>> {
    let displs: Vec<i32> = counts
        .iter()
        .scan(0, |at, &c| Some(std::mem::replace(at, *at + c)))
        .collect();
    let mut all = vec![0u8; counts.iter().map(|&c| c as usize).sum()];
    collect(&mut PartitionMut::new(&mut all[..], counts, displs.clone()));
    counts
        .iter()
        .zip(&displs)
        .map(|(&c, &d)| all[d as usize + 1..(d + c) as usize].to_vec())
        .collect()
}

impl MpiCluster {
    fn sum(&self, values: &mut [f32]) {
        let mine = values.to_vec();
        self.world
            .all_reduce_into(&mine[..], values, SystemOperation::sum());
    }
}

/// Initializes MPI and installs its world as the library's cluster; the returned universe finalizes MPI
/// when dropped, after the command has run.
pub fn install() -> Option<Universe> {
    let (universe, _) = mpi::initialize_with_threading(mpi::Threading::Serialized)?;
    let world = universe.world();
    let (rank, size) = (world.rank() as usize, world.size() as usize);
    nerfjit::cluster::install(Box::new(MpiCluster { world, rank, size }));
    Some(universe)
}
