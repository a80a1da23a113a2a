//! [`Graph::validate`]: the structural rules every graph must keep before it is compiled, checked in one
//! pass. Passes that build or transform graphs (lowering, autodiff, compaction) keep them by construction;
//! the JIT checks them in debug builds, and the property tests check every graph they generate.

use crate::ir::{Graph, Op, V};

impl Graph {
    /// Checks the graph's structure: every node reads only earlier nodes; inputs are below `n_inputs`;
    /// a dense node's operand list has its input length; a pick reads an output that its multi-valued
    /// node (a dense product or a grid read) has, and multi-valued nodes are read only through picks;
    /// outputs, reductions, outer products and scatters read existing single values, and outer products
    /// and scatters add only to existing reductions. Says what is wrong with the first broken rule.
    pub fn validate(&self) -> Result<(), String> {
        let ops = self.ops();
        let n = ops.len();
        let exists = |v: V, what: &dyn Fn() -> String| -> Result<(), String> {
            if (v.0 as usize) < n {
                Ok(())
            } else {
                Err(format!("{} reads node {} of a graph of {n}", what(), v.0))
            }
        };
        let single = |v: V, what: &dyn Fn() -> String| -> Result<(), String> {
            exists(v, what)?;
            match ops[v.0 as usize] {
                Op::Dense(_) | Op::Grid(_) => Err(format!(
                    "{} reads multi-valued node {} directly, not through a pick",
                    what(),
                    v.0
                )),
                _ => Ok(()),
            }
        };
        for (i, op) in ops.iter().enumerate() {
            let node = || format!("node {i} ({})", op.name());
            if let Op::Dense(d) = op {
                let Some(list) = self.lists().get(d.x.0 as usize) else {
                    return Err(format!("{} reads list {}, which does not exist", node(), d.x.0));
                };
                if list.len() != d.n_in() {
                    return Err(format!(
                        "{} multiplies {} values by a {}×{} matrix{}",
                        node(),
                        list.len(),
                        d.rows,
                        d.cols,
                        if d.transposed { " transposed" } else { "" }
                    ));
                }
            }
            for a in self.args(op) {
                if a.0 as usize >= i {
                    return Err(format!(
                        "{} reads node {}, which does not come before it",
                        node(),
                        a.0
                    ));
                }
                if !matches!(op, Op::Pick(..)) {
                    single(a, &node)?;
                }
            }
            match *op {
                Op::Input(k) if k >= self.n_inputs => {
                    return Err(format!("{} reads input {k} of {}", node(), self.n_inputs));
                }
                Op::Pick(of, k) => {
                    let outputs = match ops[of.0 as usize] {
                        Op::Dense(d) => d.n_out(),
                        Op::Grid(r) => r.spec.n_outputs(),
                        other => {
                            return Err(format!(
                                "{} picks from node {} ({}), which has one value",
                                node(),
                                of.0,
                                other.name()
                            ))
                        }
                    };
                    if k as usize >= outputs {
                        return Err(format!(
                            "{} picks output {k} of node {}, which has {outputs}",
                            node(),
                            of.0
                        ));
                    }
                }
                _ => {}
            }
        }
        for (k, &v) in self.outputs.iter().enumerate() {
            single(v, &|| format!("output {k}"))?;
        }
        let n_reductions = self.reductions.len();
        for (k, &v) in self.reductions.iter().enumerate() {
            single(v, &|| format!("reduction {k}"))?;
        }
        for (k, outer) in self.outer.iter().enumerate() {
            let what = || format!("outer product {k}");
            for &v in outer.left.iter().chain(&outer.right) {
                single(v, &what)?;
            }
            let end = outer.target as usize + outer.left.len() * outer.right.len();
            if end > n_reductions {
                return Err(format!("{} adds up to reduction {end} of {n_reductions}", what()));
            }
        }
        for (k, scatter) in self.scatter.iter().enumerate() {
            let what = || format!("scatter {k}");
            for &v in scatter.read.p.iter().chain(&scatter.cotangent) {
                single(v, &what)?;
            }
            if scatter.cotangent.len() != scatter.read.spec.n_outputs() {
                return Err(format!(
                    "{} has {} cotangents for a read of {} outputs",
                    what(),
                    scatter.cotangent.len(),
                    scatter.read.spec.n_outputs()
                ));
            }
            let end = u64::from(scatter.read.spec.table) + scatter.read.spec.n_params();
            if end > n_reductions as u64 {
                return Err(format!("{} adds up to reduction {end} of {n_reductions}", what()));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use crate::ir::{Graph, Op, Outer, V};

    fn graph() -> Graph {
        let mut g = Graph::new();
        let x = g.input(0);
        let y = g.push(Op::Mul(x, x));
        g.outputs.push(y);
        g
    }

    #[test]
    fn built_graphs_are_valid() {
        let mut g = graph();
        let w = g.dense(0, 2, 1, false, &[V(0)]);
        let out = g.push(Op::Add(w[0], w[1]));
        g.outputs.push(out);
        assert_eq!(g.validate(), Ok(()));
    }

    #[test]
    fn each_broken_rule_is_named() {
        let mut g = graph();
        g.outputs.push(V(7));
        assert_eq!(g.validate(), Err("output 1 reads node 7 of a graph of 2".into()));

        let mut g = graph();
        g.n_inputs = 0;
        assert_eq!(g.validate(), Err("node 0 (input) reads input 0 of 0".into()));

        let mut g = graph();
        let d = g.dense(0, 2, 1, false, &[V(0)]);
        g.outputs.push(V(d[0].0 - 1));
        let error = g.validate().unwrap_err();
        assert!(error.contains("reads multi-valued node"), "{error}");

        let mut g = graph();
        g.reductions.push(V(1));
        g.outer.push(Outer {
            target: 0,
            left: vec![V(0), V(1)],
            right: vec![V(0)],
        });
        assert_eq!(
            g.validate(),
            Err("outer product 0 adds up to reduction 2 of 1".into())
        );
    }
}
