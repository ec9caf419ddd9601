//! The short description of a graph that `vesselflow demo` prints, and every run
//! on stderr in one line: counts that show at a glance whether the topology is
//! right (components, independent cycles, junctions, endpoints).

use petgraph::unionfind::UnionFind;
use std::fmt;
use vesselflow::Skeleton;

/// Topological counts of a centreline graph.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct GraphSummary {
    pub nodes: usize,
    pub edges: usize,
    /// Connected components (isolated nodes count as one each).
    pub components: usize,
    /// Independent cycles (cyclomatic number `E - N + components`).
    pub cycles: usize,
    /// Nodes of degree >= 3.
    pub junctions: usize,
    /// Nodes of degree 1.
    pub endpoints: usize,
}

impl GraphSummary {
    pub(crate) fn of(skel: &Skeleton) -> GraphSummary {
        let nodes = skel.len();
        let mut sets = UnionFind::<usize>::new(nodes);
        for &[a, b] in &skel.edges {
            sets.union(a, b);
        }
        let components = (0..nodes).filter(|&i| sets.find_mut(i) == i).count();
        let degrees = skel.degrees();
        GraphSummary {
            nodes,
            edges: skel.edges.len(),
            components,
            cycles: (skel.edges.len() + components).saturating_sub(nodes),
            junctions: degrees.iter().filter(|&&d| d >= 3).count(),
            endpoints: degrees.iter().filter(|&&d| d == 1).count(),
        }
    }
}

impl GraphSummary {
    /// The counts in one line, e.g. "12 nodes, 11 edges, 1 component, 0 independent
    /// cycles, 1 junction, 3 endpoints".
    pub(crate) fn line(&self) -> String {
        let count = |n: usize, one: &str, many: &str| format!("{n} {}", if n == 1 { one } else { many });
        [
            count(self.nodes, "node", "nodes"),
            count(self.edges, "edge", "edges"),
            count(self.components, "component", "components"),
            count(self.cycles, "independent cycle", "independent cycles"),
            count(self.junctions, "junction", "junctions"),
            count(self.endpoints, "endpoint", "endpoints"),
        ]
        .join(", ")
    }
}

impl fmt::Display for GraphSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "nodes               {}", self.nodes)?;
        writeln!(f, "edges               {}", self.edges)?;
        writeln!(f, "components          {}", self.components)?;
        writeln!(f, "independent cycles  {}", self.cycles)?;
        writeln!(f, "junctions           {}", self.junctions)?;
        write!(f, "endpoints           {}", self.endpoints)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn graph(nodes: usize, edges: &[[usize; 2]]) -> Skeleton {
        Skeleton {
            positions: vec![[0.0; 3]; nodes],
            radii: vec![1.0; nodes],
            edges: edges.to_vec(),
            ..Default::default()
        }
    }

    #[test]
    fn triangle_with_a_tail_and_an_isolated_node() {
        // 0-1-2-0 triangle, 2-3 tail, 4 alone, 5-6 separate edge.
        let s = GraphSummary::of(&graph(7, &[[0, 1], [1, 2], [0, 2], [2, 3], [5, 6]]));
        assert_eq!(s, GraphSummary { nodes: 7, edges: 5, components: 3, cycles: 1, junctions: 1, endpoints: 3 });
    }

    #[test]
    fn two_loops_sharing_a_node_and_the_empty_graph() {
        let s = GraphSummary::of(&graph(5, &[[0, 1], [1, 2], [2, 0], [2, 3], [3, 4], [4, 2]]));
        assert_eq!((s.components, s.cycles, s.junctions, s.endpoints), (1, 2, 1, 0));
        let e = GraphSummary::of(&graph(0, &[]));
        assert_eq!((e.nodes, e.components, e.cycles), (0, 0, 0));
    }

    #[test]
    fn one_line_counts_in_words_singular_and_plural() {
        let s = GraphSummary::of(&graph(7, &[[0, 1], [1, 2], [0, 2], [2, 3], [5, 6]]));
        assert_eq!(s.line(), "7 nodes, 5 edges, 3 components, 1 independent cycle, 1 junction, 3 endpoints");
        let e = GraphSummary::of(&graph(1, &[]));
        assert_eq!(e.line(), "1 node, 0 edges, 1 component, 0 independent cycles, 0 junctions, 0 endpoints");
    }
}
