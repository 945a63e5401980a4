//! What the wiring allows to run at the same time (`caviar-core validate` prints it).
//!
//! The engine runs the stages of a step in order and the modules of one stage at once
//! (see [`crate::engine`]). From what each module subscribes to and declares publishing,
//! two questions, answered without running anything:
//!
//! * **Within a step:** which modules of different stages have no data path between them,
//!   direct or through other modules. Put in one stage they would run at once: Rust
//!   modules and NATS workers in parallel, in-process Python plugins still one after the
//!   other (one interpreter lock), though a GPU keeps working on what a plugin queued.
//! * **Across steps:** which module of step k+1 does not depend, even indirectly, on a
//!   module of a later stage of step k. Only such a module could start while that later
//!   stage still runs: a detector of step k on the CPU while step k+1's rays are traced on
//!   the GPU needs the ray tracer of step k+1 not to depend on the detector of step k.
//!
//! The rules are the engine's visibility: a message of stage s reaches the later stages
//! of the same step, and stage s and the earlier ones at their next step; and every module
//! depends on its own previous step (its state). Modules that run every n-th step are
//! treated as running every step (the answer holds for the steps where they do).

use std::collections::VecDeque;

use crate::assembly::{patterns, wiring, Unbuilt};
use crate::config::LoadedConfig;
use crate::engine::ModuleSpec;
use crate::topic::Pattern;

/// Pairs listed per answer, at most (the rest are counted).
const LISTED: usize = 12;

/// A module as the analysis sees it.
pub struct Node {
    pub name: String,
    /// Index of its stage in `episode.stages`.
    pub stage: usize,
    pub subscribe: Vec<Pattern>,
    /// `None`: not declared (it may publish anything).
    pub publishes: Option<Vec<Pattern>>,
}

/// The analysis of a configuration's modules, as lines for people.
pub fn concurrency(cfg: &LoadedConfig, specs: &[ModuleSpec], unbuilt: Unbuilt) -> Vec<String> {
    let stages = &cfg.config.episode.stages;
    let nodes: Vec<Node> = wiring(cfg, specs, unbuilt)
        .into_iter()
        .map(|w| Node {
            stage: cfg
                .config
                .modules
                .get(&w.name)
                .and_then(|m| stages.iter().position(|s| *s == m.stage))
                .unwrap_or(0),
            subscribe: patterns(&w.subscribe),
            publishes: w.publishes.as_deref().map(patterns),
            name: w.name,
        })
        .collect();
    analyse(&nodes)
}

/// An edge of the two-step graph: to `to`, because of `topic` (empty: the module's own
/// previous step).
struct Edge {
    to: usize,
    topic: String,
}

/// The two-step graph: node `m` is module m at step k, node `n + m` at step k + 1.
struct Graph<'a> {
    nodes: &'a [Node],
    edges: Vec<Vec<Edge>>,
}

impl<'a> Graph<'a> {
    fn new(nodes: &'a [Node]) -> Self {
        let n = nodes.len();
        let mut edges: Vec<Vec<Edge>> = (0..2 * n).map(|_| Vec::new()).collect();
        for (a, from) in nodes.iter().enumerate() {
            edges[a].push(Edge {
                to: n + a,
                topic: String::new(),
            });
            for (b, to) in nodes.iter().enumerate() {
                let Some(topic) = reads(to, from).filter(|_| a != b) else {
                    continue;
                };
                if from.stage < to.stage {
                    edges[a].push(Edge {
                        to: b,
                        topic: topic.clone(),
                    });
                    edges[n + a].push(Edge { to: n + b, topic });
                } else {
                    edges[a].push(Edge { to: n + b, topic });
                }
            }
        }
        Graph { nodes, edges }
    }

    /// The path from node `from` to node `to`, as (node, the topic of the edge into it);
    /// `None` when there is none.
    fn path(&self, from: usize, to: usize) -> Option<Vec<(usize, String)>> {
        let mut came: Vec<Option<(usize, &str)>> = vec![None; self.edges.len()];
        let mut queue = VecDeque::from([from]);
        let mut seen = vec![false; self.edges.len()];
        seen[from] = true;
        while let Some(u) = queue.pop_front() {
            if u == to {
                let mut path = vec![(to, String::new())];
                let mut v = to;
                while let Some((p, topic)) = came[v] {
                    path.last_mut().expect("one entry at least").1 = topic.to_string();
                    path.push((p, String::new()));
                    v = p;
                }
                path.reverse();
                return Some(path);
            }
            for e in &self.edges[u] {
                if !seen[e.to] {
                    seen[e.to] = true;
                    came[e.to] = Some((u, e.topic.as_str()));
                    queue.push_back(e.to);
                }
            }
        }
        None
    }

    /// `detector → mission ('mission.command') → uav @k+1 ('…')`.
    fn describe(&self, path: &[(usize, String)]) -> String {
        let n = self.nodes.len();
        let mut text = String::new();
        for (i, (node, _)) in path.iter().enumerate() {
            if i > 0 {
                let topic = &path[i].1;
                let why = if topic.is_empty() {
                    " (its own state)".to_string()
                } else {
                    format!(" ('{topic}')")
                };
                text.push_str(&format!("{why} → "));
            }
            text.push_str(&self.nodes[node % n].name);
            if *node >= n {
                text.push_str(" @k+1");
            }
        }
        text
    }
}

/// The first of `reader`'s subscriptions that something `writer` publishes could match.
fn reads(reader: &Node, writer: &Node) -> Option<String> {
    let published = writer.publishes.as_ref()?;
    reader
        .subscribe
        .iter()
        .find(|s| published.iter().any(|p| p.overlaps(s)))
        .map(|s| s.as_str().to_string())
}

fn listed(pairs: &[String]) -> String {
    let mut text = pairs
        .iter()
        .take(LISTED)
        .cloned()
        .collect::<Vec<_>>()
        .join("; ");
    if pairs.len() > LISTED {
        text.push_str(&format!("; and {} more", pairs.len() - LISTED));
    }
    text
}

/// The answers for these modules (see the module's documentation).
pub fn analyse(nodes: &[Node]) -> Vec<String> {
    let undeclared: Vec<&str> = nodes
        .iter()
        .filter(|m| m.publishes.is_none())
        .map(|m| m.name.as_str())
        .collect();
    if !undeclared.is_empty() {
        return vec![format!(
            "cannot tell what may run at once: {} do(es) not declare what it publishes",
            undeclared.join(", ")
        )];
    }
    let graph = Graph::new(nodes);
    let n = nodes.len();
    let mut within = Vec::new();
    let mut across = Vec::new();
    let mut blocked: Option<(usize, usize)> = None;
    for (a, late) in nodes.iter().enumerate() {
        for (b, early) in nodes.iter().enumerate() {
            if early.stage >= late.stage {
                continue;
            }
            if graph.path(b, a).is_none() {
                within.push(format!("{} and {}", early.name, late.name));
            }
            if graph.path(a, n + b).is_none() {
                across.push(format!(
                    "{} of step k+1 during {} of step k",
                    early.name, late.name
                ));
            } else if blocked
                .is_none_or(|(x, y)| late.stage - early.stage > nodes[x].stage - nodes[y].stage)
            {
                blocked = Some((a, b)); // the example to show: the stages farthest apart
            }
        }
    }
    let mut lines = Vec::new();
    lines.push(if within.is_empty() {
        "within a step: each module depends on every earlier stage (no two could share a stage)"
            .to_string()
    } else {
        format!(
            "within a step, no data path between (they could share a stage): {}",
            listed(&within)
        )
    });
    lines.push(match (across.is_empty(), blocked) {
        (false, _) => format!("across steps, could overlap: {}", listed(&across)),
        (true, Some((a, b))) => format!(
            "across steps: nothing could overlap; step k+1 waits for step k, e.g. {}",
            graph.describe(&graph.path(a, n + b).expect("blocked pairs have a path"))
        ),
        (true, None) => "across steps: nothing could overlap (one stage)".to_string(),
    });
    lines
}

#[cfg(test)]
mod tests {
    use super::*;

    fn node(name: &str, stage: usize, subscribe: &[&str], publishes: &[&str]) -> Node {
        let p = |t: &[&str]| t.iter().map(|x| Pattern::new(x).unwrap()).collect();
        Node {
            name: name.into(),
            stage,
            subscribe: p(subscribe),
            publishes: Some(p(publishes)),
        }
    }

    /// The SAR loop: the mission's decision of step k moves the UAV of step k+1, so the
    /// ray tracer of step k+1 waits for the detector of step k.
    #[test]
    fn a_closed_loop_allows_no_overlap_across_steps() {
        let nodes = [
            node("uav", 0, &["mission.command"], &["uav.position"]),
            node("camera", 1, &["uav.position"], &["camera.image"]),
            node("rays", 2, &["uav.position"], &["channel"]),
            node("detector", 3, &["camera.image", "channel"], &["detections"]),
            node("mission", 4, &["detections"], &["mission.command"]),
        ];
        let lines = analyse(&nodes);
        assert_eq!(
            lines[0],
            "within a step, no data path between (they could share a stage): camera and rays"
        );
        assert_eq!(
            lines[1],
            "across steps: nothing could overlap; step k+1 waits for step k, e.g. mission \
             ('mission.command') → uav @k+1"
        );
    }

    /// Without the feedback (the UAV flies its route whatever is detected), the next
    /// step's flight, camera and rays may start while the detector and the mission run.
    #[test]
    fn an_open_loop_lets_the_next_rays_run_beside_the_detector() {
        let nodes = [
            node("uav", 0, &[], &["uav.position"]),
            node("rays", 1, &["uav.position"], &["channel"]),
            node("detector", 2, &["channel"], &["detections"]),
            node("mission", 3, &["detections"], &["mission.result"]),
        ];
        let lines = analyse(&nodes);
        assert!(
            lines[0].starts_with("within a step: each module depends"),
            "{}",
            lines[0]
        );
        assert!(
            lines[1].contains("rays of step k+1 during detector of step k"),
            "{}",
            lines[1]
        );
        assert!(
            lines[1].contains("uav of step k+1 during mission of step k"),
            "{}",
            lines[1]
        );
        // The detector of step k+1 needs its own step k: it never overlaps itself.
        assert!(
            !lines[1].contains("detector of step k+1 during detector"),
            "{}",
            lines[1]
        );
    }

    #[test]
    fn an_indirect_path_through_a_later_stage_counts() {
        // a of step k+1 reads nothing of c, but it reads b within its step, and b reads c
        // of the step before: a @k+1 waits for b @k+1, which waits for c @k.
        let nodes = [
            node("b", 0, &["c.out"], &["b.out"]),
            node("a", 1, &["b.out"], &["a.out"]),
            node("c", 2, &["a.out"], &["c.out"]),
        ];
        let lines = analyse(&nodes);
        assert_eq!(
            lines[1],
            "across steps: nothing could overlap; step k+1 waits for step k, e.g. c ('c.out') → b @k+1"
        );
        let mut open = nodes;
        open[0].subscribe.clear();
        assert!(analyse(&open)[1].contains("b of step k+1 during c of step k"));
    }

    #[test]
    fn a_module_that_does_not_declare_its_topics_leaves_the_question_open() {
        let mut nodes = [node("a", 0, &[], &["x"]), node("b", 1, &["x"], &[])];
        nodes[1].publishes = None;
        assert_eq!(
            analyse(&nodes),
            ["cannot tell what may run at once: b do(es) not declare what it publishes"]
        );
    }
}
