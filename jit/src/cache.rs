//! A cache of compiled kernels, keyed by their graph, so that each kernel is compiled once per process.

use std::collections::HashMap;
use std::hash::{Hash, Hasher};
use std::sync::{Arc, Mutex};

use nerfjit_dsl::ir::Graph;

use crate::kernel::{JitError, Kernel, Options};

/// The kernels whose graphs share one fingerprint, with their graphs (to tell collisions apart).
type Bucket = Vec<(Graph, Arc<Kernel>)>;

/// Compiled kernels by graph.
#[derive(Default)]
pub struct KernelCache {
    entries: Mutex<HashMap<u64, Bucket>>,
}

fn same(a: &Graph, b: &Graph) -> bool {
    a.ops() == b.ops()
        && a.lists() == b.lists()
        && a.outputs == b.outputs
        && a.reductions == b.reductions
        && a.outer == b.outer
        && a.scatter == b.scatter
        && a.n_inputs == b.n_inputs
}

fn fingerprint(g: &Graph) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    g.ops().hash(&mut h);
    g.outputs.hash(&mut h);
    g.reductions.hash(&mut h);
    g.lists().hash(&mut h);
    g.outer.hash(&mut h);
    g.scatter.hash(&mut h);
    g.n_inputs.hash(&mut h);
    h.finish()
}

impl KernelCache {
    /// An empty cache.
    pub fn new() -> Self {
        Self::default()
    }

    /// The kernel of `graph`, compiled on first request. Threads compile different kernels at once (the
    /// cache is not locked while compiling); two threads asking for the same new kernel at once may both
    /// compile it, and both get the one cached first.
    pub fn get(&self, graph: &Graph, options: Options) -> Result<Arc<Kernel>, JitError> {
        let graph = graph.compact();
        let key = fingerprint(&graph);
        if let Some(kernel) = self.find(key, &graph) {
            return Ok(kernel);
        }
        let kernel = Arc::new(Kernel::compile(&graph, options)?);
        let mut entries = self.entries.lock().unwrap_or_else(|e| e.into_inner());
        let bucket = entries.entry(key).or_default();
        if let Some((_, first)) = bucket.iter().find(|(g, _)| same(g, &graph)) {
            return Ok(first.clone());
        }
        bucket.push((graph, kernel.clone()));
        Ok(kernel)
    }

    /// The cached kernel of a compacted graph with fingerprint `key`.
    fn find(&self, key: u64, graph: &Graph) -> Option<Arc<Kernel>> {
        let entries = self.entries.lock().unwrap_or_else(|e| e.into_inner());
        let bucket = entries.get(&key)?;
        bucket
            .iter()
            .find(|(g, _)| same(g, graph))
            .map(|(_, k)| k.clone())
    }

    /// How many kernels are cached.
    pub fn len(&self) -> usize {
        self.entries.lock().map_or(0, |e| e.values().map(Vec::len).sum())
    }

    /// Whether the cache is empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}
