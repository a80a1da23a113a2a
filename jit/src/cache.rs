//! A cache of compiled kernels, keyed by their graph and compile options, so that each kernel is compiled
//! once per cache (`nerfjit run` keeps one for all of a script's blocks).

use std::collections::HashMap;
use std::hash::{Hash, Hasher};
use std::sync::{Arc, Mutex};

use nerfjit_dsl::ir::Graph;

use crate::kernel::{JitError, Kernel, Options};

/// The kernels whose graphs and options share one fingerprint, with their graphs and options (to tell
/// collisions apart).
type Bucket = Vec<(Graph, Options, Arc<Kernel>)>;

/// Compiled kernels by graph and options.
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

fn fingerprint(g: &Graph, options: Options) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    options.hash(&mut h);
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

    /// The kernel of `graph` compiled with `options`, compiled on first request. Threads compile different kernels at once (the
    /// cache is not locked while compiling); two threads asking for the same new kernel at once may both
    /// compile it, and both get the one cached first.
    pub fn get(&self, graph: &Graph, options: Options) -> Result<Arc<Kernel>, JitError> {
        let graph = graph.compact();
        let key = fingerprint(&graph, options);
        if let Some(kernel) = self.find(key, &graph, options) {
            return Ok(kernel);
        }
        let kernel = Arc::new(Kernel::compile(&graph, options)?);
        let mut entries = self.entries.lock().unwrap_or_else(|e| e.into_inner());
        let bucket = entries.entry(key).or_default();
        if let Some((_, _, first)) = bucket.iter().find(|(g, o, _)| *o == options && same(g, &graph)) {
            return Ok(first.clone());
        }
        bucket.push((graph, options, kernel.clone()));
        Ok(kernel)
    }

    /// The cached kernel of a compacted graph and options with fingerprint `key`.
    fn find(&self, key: u64, graph: &Graph, options: Options) -> Option<Arc<Kernel>> {
        let entries = self.entries.lock().unwrap_or_else(|e| e.into_inner());
        let bucket = entries.get(&key)?;
        bucket
            .iter()
            .find(|(g, o, _)| *o == options && same(g, graph))
            .map(|(_, _, k)| k.clone())
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

#[cfg(test)]
mod tests {
    use super::*;
    use nerfjit_dsl::ir::Op;

    fn square() -> Graph {
        let mut g = Graph::new();
        let x = g.input(0);
        let y = g.push(Op::Mul(x, x));
        g.outputs = vec![y];
        g.n_inputs = 1;
        g
    }

    #[test]
    fn a_kernel_is_compiled_once_per_graph_and_options() {
        let cache = KernelCache::new();
        let plain = cache.get(&square(), Options::default()).unwrap();
        let again = cache.get(&square(), Options::default()).unwrap();
        assert!(Arc::ptr_eq(&plain, &again));
        assert_eq!(cache.len(), 1);
        // Asking for the Cranelift text is another kernel: the cached one kept none.
        let with_text = cache
            .get(
                &square(),
                Options {
                    keep_clif: true,
                    ..Options::default()
                },
            )
            .unwrap();
        assert!(!Arc::ptr_eq(&plain, &with_text));
        assert!(plain.stats().clif.is_none());
        assert!(with_text.stats().clif.is_some());
        assert_eq!(cache.len(), 2);
    }
}
