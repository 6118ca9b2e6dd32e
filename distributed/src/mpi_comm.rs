//! [`Communicator`] over MPI (the `mpi` crate).

use mpi::datatype::PartitionMut;
use mpi::traits::{Communicator as _, CommunicatorCollectives as _};
use mpi::Count;

use crate::Communicator;

/// MPI's world communicator. Made once per process by [`MpiComm::init`]; dropping it
/// finalizes MPI.
pub struct MpiComm {
    // Dropped first: the world before the environment that finalizes MPI.
    world: mpi::topology::SimpleCommunicator,
    _universe: mpi::environment::Universe,
}

impl MpiComm {
    /// Initializes MPI. Errors if it was already initialized in this process.
    pub fn init() -> Result<Self, String> {
        let universe = mpi::initialize().ok_or("MPI is already initialized in this process")?;
        let world = universe.world();
        Ok(MpiComm {
            world,
            _universe: universe,
        })
    }
}

impl Communicator for MpiComm {
    fn rank(&self) -> usize {
        self.world.rank() as usize
    }

    fn size(&self) -> usize {
        self.world.size() as usize
    }

    fn all_gather_bytes(&self, local: &[u8]) -> Vec<Vec<u8>> {
        let n = self.size();
        let mut counts = vec![0 as Count; n];
        let len = Count::try_from(local.len()).expect("a rank's bytes fit MPI's 32-bit count");
        self.world.all_gather_into(&len, &mut counts[..]);
        let displs: Vec<Count> = counts
            .iter()
            .scan(0, |at, &c| {
                let d = *at;
                *at += c;
                Some(d)
            })
            .collect();
        let total: usize = counts.iter().map(|&c| c as usize).sum();
        // MPI counts are 32-bit: a gather past 2 GiB would wrap.
        assert!(
            total <= Count::MAX as usize,
            "MpiComm::all_gather_bytes: {total} bytes from all ranks, more than MPI's 32-bit \
             counts allow; gather fewer outputs per world or sums instead"
        );
        let mut buf = vec![0u8; total];
        {
            let mut part = PartitionMut::new(&mut buf[..], counts.clone(), &displs[..]);
            self.world.all_gather_varcount_into(local, &mut part);
        }
        counts
            .iter()
            .zip(&displs)
            .map(|(&c, &d)| buf[d as usize..(d + c) as usize].to_vec())
            .collect()
    }
}
