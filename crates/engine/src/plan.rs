//! Which stages run, and in what order.

use std::collections::{BTreeMap, BTreeSet};

use crate::spec::Pipeline;

/// Upstream stage names of each stage (its references).
pub fn deps(p: &Pipeline) -> BTreeMap<String, BTreeSet<String>> {
    p.stages
        .iter()
        .map(|s| {
            (
                s.name.clone(),
                s.refs.values().map(|(up, _)| up.clone()).collect(),
            )
        })
        .collect()
}

/// A cycle as stage names, first repeated at the end
/// (`a -> b -> a`), or `None`.
pub fn find_cycle(p: &Pipeline) -> Option<Vec<String>> {
    let d = deps(p);
    // 0 = unvisited, 1 = on the stack, 2 = done.
    let mut state: BTreeMap<&str, u8> = BTreeMap::new();
    let mut stack: Vec<String> = Vec::new();
    fn visit<'a>(
        n: &'a str,
        d: &'a BTreeMap<String, BTreeSet<String>>,
        state: &mut BTreeMap<&'a str, u8>,
        stack: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        match state.get(n) {
            Some(2) => return None,
            Some(1) => {
                let i = stack.iter().position(|x| x == n).unwrap_or(0);
                let mut c: Vec<String> = stack[i..].to_vec();
                c.push(n.to_string());
                return Some(c);
            }
            _ => {}
        }
        state.insert(n, 1);
        stack.push(n.to_string());
        if let Some(ups) = d.get(n) {
            for u in ups {
                if let Some(c) = visit(u, d, state, stack) {
                    return Some(c);
                }
            }
        }
        stack.pop();
        state.insert(n, 2);
        None
    }
    for s in &p.stages {
        if let Some(mut c) = visit(&s.name, &d, &mut state, &mut stack) {
            // Report in data-flow order (upstream first).
            c.reverse();
            return Some(c);
        }
    }
    None
}

/// The stages the requested outputs need (themselves and all upstream).
pub fn needed(p: &Pipeline) -> BTreeSet<String> {
    let d = deps(p);
    let mut out = BTreeSet::new();
    let mut todo: Vec<String> = p.outputs.clone();
    while let Some(n) = todo.pop() {
        if out.insert(n.clone()) {
            if let Some(ups) = d.get(&n) {
                todo.extend(ups.iter().cloned());
            }
        }
    }
    out
}

/// Needed stages in an order where every stage follows its inputs (ties
/// in file order). The pipeline is acyclic (checked at load).
pub fn order(p: &Pipeline) -> Vec<String> {
    let need = needed(p);
    let d = deps(p);
    let mut done: BTreeSet<String> = BTreeSet::new();
    let mut out = Vec::new();
    while out.len() < need.len() {
        let before = out.len();
        for s in &p.stages {
            if need.contains(&s.name)
                && !done.contains(&s.name)
                && d[&s.name].iter().all(|u| done.contains(u))
            {
                done.insert(s.name.clone());
                out.push(s.name.clone());
            }
        }
        if out.len() == before {
            break; // unreachable for an acyclic pipeline
        }
    }
    out
}
