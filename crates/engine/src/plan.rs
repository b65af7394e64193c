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

/// Needed stages in an order where every stage follows its inputs: the
/// order of repeated passes over the file, each taking every stage whose
/// inputs are taken (stage i lands in pass max over its inputs u of
/// pass(u), plus one when u comes later in the file; ties in file order),
/// computed in O((stages + references) log stages). The pipeline is
/// acyclic (checked at load).
pub fn order(p: &Pipeline) -> Vec<String> {
    let need = needed(p);
    let idx = p.positions();
    let n = p.stages.len();
    let mut ups: Vec<Vec<usize>> = vec![Vec::new(); n];
    let mut downs: Vec<Vec<usize>> = vec![Vec::new(); n];
    let mut waiting = vec![0usize; n];
    for (i, s) in p.stages.iter().enumerate() {
        if !need.contains(&s.name) {
            continue;
        }
        let mut us: Vec<usize> = s
            .refs
            .values()
            .filter_map(|(u, _)| idx.get(u.as_str()).copied())
            .collect();
        us.sort_unstable();
        us.dedup();
        for &u in &us {
            downs[u].push(i);
        }
        waiting[i] = us.len();
        ups[i] = us;
    }
    let mut pass = vec![0usize; n];
    let mut todo: Vec<usize> = (0..n)
        .filter(|&i| need.contains(&p.stages[i].name) && waiting[i] == 0)
        .collect();
    let mut taken = Vec::new();
    while let Some(i) = todo.pop() {
        pass[i] = ups[i]
            .iter()
            .map(|&u| pass[u] + usize::from(u > i))
            .max()
            .unwrap_or(0);
        taken.push(i);
        for &d in &downs[i] {
            waiting[d] -= 1;
            if waiting[d] == 0 {
                todo.push(d);
            }
        }
    }
    taken.sort_unstable_by_key(|&i| (pass[i], i));
    taken
        .into_iter()
        .map(|i| p.stages[i].name.clone())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The definition: repeated passes in file order.
    fn by_passes(p: &Pipeline) -> Vec<String> {
        let need = needed(p);
        let d = deps(p);
        let mut done: BTreeSet<String> = BTreeSet::new();
        let mut out = Vec::new();
        while out.len() < need.len() {
            for s in &p.stages {
                if need.contains(&s.name)
                    && !done.contains(&s.name)
                    && d[&s.name].iter().all(|u| done.contains(u))
                {
                    done.insert(s.name.clone());
                    out.push(s.name.clone());
                }
            }
        }
        out
    }

    #[test]
    fn order_is_the_passes_order_on_random_dags() {
        let mut x = 0x2545f4914f6cdd1du64;
        let mut rnd = move |m: usize| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x % m as u64) as usize
        };
        for case in 0..200 {
            let n = 1 + rnd(12);
            // A random DAG over a random permutation, written in file order.
            let mut perm: Vec<usize> = (0..n).collect();
            for i in (1..n).rev() {
                perm.swap(i, rnd(i + 1));
            }
            let mut stages = Vec::new();
            for (pos, &topo) in perm.iter().enumerate() {
                let mut refs = BTreeMap::new();
                for (k, &other) in perm.iter().enumerate() {
                    if other < topo && rnd(3) == 0 {
                        refs.insert(format!("in{k}"), (format!("s{k}"), "out".to_string()));
                    }
                }
                stages.push(crate::spec::Stage {
                    name: format!("s{pos}"),
                    kind: "k".into(),
                    loc: Default::default(),
                    params: Default::default(),
                    refs,
                });
            }
            let outputs = (0..n)
                .filter(|_| rnd(2) == 0)
                .map(|i| format!("s{i}"))
                .collect();
            let p = Pipeline {
                name: "t".into(),
                file: Default::default(),
                stages,
                outputs,
                remote_cache: None,
                dataset: None,
            };
            assert_eq!(order(&p), by_passes(&p), "case {case}");
        }
    }
}
