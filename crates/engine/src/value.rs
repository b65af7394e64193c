//! Parameter values as written in a pipeline file, with where they were
//! written.

use std::fmt;

use saphyr::{LoadableYamlNode, MarkedYamlOwned, ScalarOwned, YamlDataOwned};

/// A 1-based line and column in a pipeline file (0, 0: not from a file,
/// e.g. a default or a `--set` override).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord)]
pub struct Loc {
    pub line: usize,
    pub col: usize,
}

impl fmt::Display for Loc {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}", self.line, self.col)
    }
}

/// A parameter value. Mappings exist only at the pipeline's structure
/// level; parameters are scalars or flat lists.
#[derive(Clone, Debug, PartialEq)]
pub enum Value {
    Null,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    List(Vec<Value>),
    Map(Vec<(String, Loc, Value, Loc)>),
}

impl Value {
    pub fn type_name(&self) -> &'static str {
        match self {
            Value::Null => "null",
            Value::Bool(_) => "a boolean",
            Value::Int(_) => "an integer",
            Value::Float(_) => "a number",
            Value::Str(_) => "a string",
            Value::List(_) => "a list",
            Value::Map(_) => "a mapping",
        }
    }

    pub fn as_f64(&self) -> Option<f64> {
        match self {
            Value::Int(i) => Some(*i as f64),
            Value::Float(f) => Some(*f),
            _ => None,
        }
    }
}

impl fmt::Display for Value {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Value::Null => write!(f, "~"),
            Value::Bool(b) => write!(f, "{b}"),
            Value::Int(i) => write!(f, "{i}"),
            Value::Float(x) => write!(f, "{x}"),
            Value::Str(s) => write!(f, "{s}"),
            Value::List(v) => {
                write!(f, "[")?;
                for (i, x) in v.iter().enumerate() {
                    if i > 0 {
                        write!(f, ", ")?;
                    }
                    write!(f, "{x}")?;
                }
                write!(f, "]")
            }
            Value::Map(m) => {
                write!(f, "{{")?;
                for (i, (k, _, v, _)) in m.iter().enumerate() {
                    if i > 0 {
                        write!(f, ", ")?;
                    }
                    write!(f, "{k}: {v}")?;
                }
                write!(f, "}}")
            }
        }
    }
}

/// Why YAML text could not become a [`Value`].
#[derive(Debug, Clone)]
pub struct ParseError {
    pub loc: Loc,
    pub message: String,
}

/// Bounds on a pipeline document, checked on the parser's event stream
/// before any value is built: nothing a few bytes of YAML ask for can
/// make the loader expand, nest or allocate beyond them.
pub mod limits {
    /// Bytes in one document (a 10,000-stage pipeline is ~1 MB).
    pub const MAX_BYTES: usize = 16 << 20;
    /// Nested mappings and sequences (a pipeline needs 4).
    pub const MAX_DEPTH: usize = 64;
    /// Entries of one mapping or items of one sequence.
    pub const MAX_ITEMS: usize = 1_000_000;
    /// Nodes (scalars, mappings, sequences) in the whole document.
    pub const MAX_NODES: usize = 4_000_000;
}

/// The document is within [`limits::MAX_BYTES`]; the error says where
/// the limit falls, as a line and column.
fn check_size(text: &str) -> Result<(), ParseError> {
    if text.len() > limits::MAX_BYTES {
        // Where the limit falls, as a line and column.
        let mut cut = limits::MAX_BYTES;
        while !text.is_char_boundary(cut) {
            cut -= 1;
        }
        let head = &text[..cut];
        let line = head.matches('\n').count() + 1;
        let col = head.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
        return Err(ParseError {
            loc: Loc { line, col },
            message: format!(
                "the document is {} bytes; a pipeline may have at most {} (limit reached here)",
                text.len(),
                limits::MAX_BYTES
            ),
        });
    }
    Ok(())
}

/// No line starts with `%`.
fn check_no_directives(text: &str) -> Result<(), ParseError> {
    // Directives (`%YAML`, `%TAG`) are refused before the scanner sees
    // them: pipelines need none, and saphyr-parser 0.0.12 loops without
    // bound, allocating, on a directive name that runs to the end of the
    // input through multi-byte characters (found by tests/fuzz.rs). A
    // line can only start with `%` as a directive or inside a quoted or
    // block scalar; the latter is refused too, with this message.
    for (i, line) in text.split('\n').enumerate() {
        let line = if i == 0 {
            line.trim_start_matches('\u{feff}')
        } else {
            line
        };
        if line.starts_with('%') {
            return Err(ParseError {
                loc: Loc {
                    line: i + 1,
                    col: 1,
                },
                message: "a line starting with `%` (a YAML directive) is not supported in \
                          pipelines; indent or quote it"
                    .into(),
            });
        }
    }
    Ok(())
}

/// Checks a document's event stream against [`limits`] and finds a key
/// given twice in one mapping (YAML forbids it; the loader would keep the
/// last silently, hiding a stage or a parameter). Aliases are refused
/// where they appear, before the loader could expand them ("billion
/// laughs"): pipelines do not use them. Syntax errors are left to the
/// loader, which reports them with its own message.
fn check_events(text: &str) -> Result<(), ParseError> {
    use saphyr_parser::Event;
    check_size(text)?;
    check_no_directives(text)?;
    // Per open container: its item count, and for mappings the keys seen
    // and whether the next node is a key.
    struct Open {
        items: usize,
        keys: Option<(std::collections::HashSet<String>, bool)>,
    }
    let mut stack: Vec<Open> = Vec::new();
    let mut nodes = 0usize;
    for ev in saphyr_parser::Parser::new_from_str(text) {
        let (ev, span) = match ev {
            Ok(e) => e,
            // The scanner stops flow collections at 255 levels, before
            // their events reach this check: the same limit, said the
            // same way.
            Err(e) if e.info().contains("recursion limit") => {
                return Err(ParseError {
                    loc: Loc {
                        line: e.marker().line(),
                        col: e.marker().col() + 1,
                    },
                    message: format!(
                        "mappings and sequences nested more than {} deep",
                        limits::MAX_DEPTH
                    ),
                })
            }
            Err(_) => return Ok(()),
        };
        let loc = Loc {
            line: span.start.line(),
            col: span.start.col() + 1,
        };
        let fail = |message: String| Err(ParseError { loc, message });
        let is_node = matches!(
            ev,
            Event::Scalar(..)
                | Event::Alias(_)
                | Event::SequenceStart(..)
                | Event::MappingStart(..)
        );
        // The node's place in its container: a mapping key or an item.
        let mut is_key = false;
        if is_node {
            nodes += 1;
            if nodes > limits::MAX_NODES {
                return fail(format!(
                    "more than {} YAML nodes in one document",
                    limits::MAX_NODES
                ));
            }
            if let Some(open) = stack.last_mut() {
                match &mut open.keys {
                    Some((_, expect_key)) => {
                        is_key = *expect_key;
                        *expect_key = !is_key;
                        if is_key {
                            open.items += 1;
                        }
                    }
                    None => open.items += 1,
                }
                if open.items > limits::MAX_ITEMS {
                    return fail(format!(
                        "more than {} entries in one mapping or sequence",
                        limits::MAX_ITEMS
                    ));
                }
            }
        }
        match ev {
            Event::Alias(_) => {
                return fail(
                    "YAML aliases (*name) are not supported in pipelines; write the value out"
                        .into(),
                )
            }
            Event::Scalar(v, ..) if is_key => {
                if let Some(Some((keys, _))) = stack.last_mut().map(|o| o.keys.as_mut()) {
                    if !keys.insert(v.to_string()) {
                        return fail(format!("`{}` is given twice in this mapping", clip(&v)));
                    }
                }
            }
            Event::SequenceStart(..) | Event::MappingStart(..) => {
                if stack.len() >= limits::MAX_DEPTH {
                    return fail(format!(
                        "mappings and sequences nested more than {} deep",
                        limits::MAX_DEPTH
                    ));
                }
                let keys =
                    matches!(ev, Event::MappingStart(..)).then(|| (Default::default(), true));
                stack.push(Open { items: 0, keys });
            }
            Event::SequenceEnd | Event::MappingEnd => {
                stack.pop();
            }
            _ => {}
        }
    }
    Ok(())
}

/// `s`, or its first characters and how long it was, for messages that
/// must not echo huge values.
pub fn clip(s: &str) -> String {
    const KEEP: usize = 80;
    match s.char_indices().nth(KEEP) {
        None => s.to_string(),
        Some((cut, _)) => format!("{}… ({} bytes)", &s[..cut], s.len()),
    }
}

/// Parses one YAML document into a located value tree, within
/// [`limits`]. A key given twice in one mapping is an error, and so is an
/// alias.
pub fn parse_yaml(text: &str) -> Result<(Value, Loc), ParseError> {
    check_events(text)?;
    let docs = MarkedYamlOwned::load_from_str(text).map_err(|e| ParseError {
        loc: Loc {
            line: e.marker().line(),
            col: e.marker().col() + 1,
        },
        message: e.info().to_string(),
    })?;
    match docs.len() {
        0 => Ok((Value::Null, Loc { line: 1, col: 1 })),
        1 => convert(&docs[0]),
        _ => Err(ParseError {
            loc: loc_of(&docs[1]),
            message: "more than one YAML document; a pipeline is one document".into(),
        }),
    }
}

fn loc_of(n: &MarkedYamlOwned) -> Loc {
    Loc {
        line: n.span.start.line(),
        col: n.span.start.col() + 1,
    }
}

fn convert(n: &MarkedYamlOwned) -> Result<(Value, Loc), ParseError> {
    let loc = loc_of(n);
    let v = match &n.data {
        YamlDataOwned::Value(s) => scalar(s, loc)?,
        YamlDataOwned::Representation(s, _, _) => Value::Str(s.clone()),
        YamlDataOwned::Sequence(seq) => {
            let mut out = Vec::with_capacity(seq.len());
            for x in seq {
                out.push(convert(x)?.0);
            }
            Value::List(out)
        }
        YamlDataOwned::Mapping(m) => {
            let mut out: Vec<(String, Loc, Value, Loc)> = Vec::with_capacity(m.len());
            for (k, v) in m {
                let kl = loc_of(k);
                let key = match &k.data {
                    YamlDataOwned::Value(ScalarOwned::String(s)) => s.clone(),
                    YamlDataOwned::Value(s) => scalar_text(s),
                    _ => {
                        return Err(ParseError {
                            loc: kl,
                            message: "mapping keys must be plain names".into(),
                        })
                    }
                };
                let (val, vl) = convert(v)?;
                out.push((key, kl, val, vl));
            }
            Value::Map(out)
        }
        YamlDataOwned::Tagged(_, inner) => convert(inner)?.0,
        YamlDataOwned::Alias(_) => {
            return Err(ParseError {
                loc,
                message: "YAML aliases are not supported in pipelines".into(),
            })
        }
        YamlDataOwned::BadValue => {
            return Err(ParseError {
                loc,
                message: "unreadable value".into(),
            })
        }
    };
    Ok((v, loc))
}

fn scalar_text(s: &ScalarOwned) -> String {
    match s {
        ScalarOwned::Null => "~".into(),
        ScalarOwned::Boolean(b) => b.to_string(),
        ScalarOwned::Integer(i) => i.to_string(),
        ScalarOwned::FloatingPoint(f) => f.to_string(),
        ScalarOwned::String(s) => s.clone(),
    }
}

fn scalar(s: &ScalarOwned, loc: Loc) -> Result<Value, ParseError> {
    Ok(match s {
        ScalarOwned::Null => Value::Null,
        ScalarOwned::Boolean(b) => Value::Bool(*b),
        ScalarOwned::Integer(i) => Value::Int(*i),
        ScalarOwned::FloatingPoint(f) => {
            let x = f.into_inner();
            if !x.is_finite() {
                return Err(ParseError {
                    loc,
                    message: format!("{x} is not a finite number"),
                });
            }
            Value::Float(x)
        }
        ScalarOwned::String(s) => Value::Str(s.clone()),
    })
}

/// Parses a `--set` value: a YAML scalar or flow sequence.
pub fn parse_override(text: &str) -> Result<Value, String> {
    match parse_yaml(text) {
        Ok((Value::Map(_), _)) => Err(format!(
            "'{}' is a mapping; give a scalar or a list",
            clip(text)
        )),
        Ok((v, _)) => Ok(v),
        Err(e) => Err(format!("'{}': {}", clip(text), e.message)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn locations_are_one_based_and_point_at_the_value() {
        let (v, _) = parse_yaml("a: 1\nb:\n  c: [1, 2.5, x]\n").unwrap();
        let Value::Map(m) = v else { panic!() };
        assert_eq!(m[0].0, "a");
        assert_eq!(m[0].1, Loc { line: 1, col: 1 });
        assert_eq!(m[0].3, Loc { line: 1, col: 4 });
        let Value::Map(inner) = &m[1].2 else { panic!() };
        assert_eq!(inner[0].1, Loc { line: 3, col: 3 });
        assert_eq!(
            inner[0].2,
            Value::List(vec![
                Value::Int(1),
                Value::Float(2.5),
                Value::Str("x".into())
            ])
        );
    }

    /// "Billion laughs": nine aliases of nine aliases of … of a list.
    /// Expanded it would be 9^12 strings; refused at the first alias.
    pub(crate) fn alias_bomb() -> String {
        let mut t = String::from("a0: &a0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n");
        for i in 1..12 {
            let refs = vec![format!("*a{}", i - 1); 9].join(", ");
            t += &format!("a{i}: &a{i} [{refs}]\n");
        }
        t + "stages:\n  x: *a11\n"
    }

    #[test]
    fn aliases_are_refused_where_they_are_not_expanded() {
        let t = std::time::Instant::now();
        let e = parse_yaml(&alias_bomb()).unwrap_err();
        assert_eq!(e.loc, Loc { line: 2, col: 10 });
        assert!(e.message.contains("aliases"), "{}", e.message);
        assert!(t.elapsed().as_secs() < 5, "refused at once");
        // A single alias is refused the same way (pipelines never use them).
        let e = parse_yaml("a: &x 1\nb: *x\n").unwrap_err();
        assert_eq!(e.loc, Loc { line: 2, col: 4 });
    }

    #[test]
    fn nesting_is_bounded_in_every_syntax() {
        let d = 8000;
        // Flow, compact block sequences, indented block mappings.
        let flow = format!("p: {}1{}\n", "[".repeat(d), "]".repeat(d));
        let compact = format!("p:\n  {}x\n", "- ".repeat(d));
        let block: String = (0..1000)
            .map(|i| format!("{}k:\n", " ".repeat(i)))
            .collect();
        for (text, line) in [(flow, 1), (compact, 2), (block, limits::MAX_DEPTH + 1)] {
            let e = parse_yaml(&text).unwrap_err();
            assert!(e.message.contains("nested more than 64"), "{}", e.message);
            assert_eq!(e.loc.line, line);
        }
        // Up to the limit is fine.
        let ok = format!(
            "p: {}1{}\n",
            "[".repeat(limits::MAX_DEPTH - 1),
            "]".repeat(limits::MAX_DEPTH - 1)
        );
        assert!(parse_yaml(&ok).is_ok());
        // So is an override, whose errors do not echo the whole text.
        let e = parse_override(&format!("{}1{}", "[".repeat(d), "]".repeat(d))).unwrap_err();
        assert!(e.contains("nested more than 64"), "{e}");
        assert!(e.len() < 300, "{e}");
    }

    #[test]
    fn size_and_collections_are_bounded() {
        let big = format!("a: \"{}\"\n", "x".repeat(limits::MAX_BYTES));
        let e = parse_yaml(&big).unwrap_err();
        assert!(e.message.contains("at most 16777216"), "{}", e.message);
        assert_eq!(
            e.loc,
            Loc {
                line: 1,
                col: limits::MAX_BYTES + 1
            }
        );
        let items = vec!["1"; limits::MAX_ITEMS + 1].join(",");
        let e = parse_yaml(&format!("a: [{items}]\n")).unwrap_err();
        assert!(
            e.message.contains("more than 1000000 entries"),
            "{}",
            e.message
        );
        assert_eq!(e.loc.line, 1);
        let items = vec!["1"; limits::MAX_ITEMS].join(",");
        assert!(parse_yaml(&format!("a: [{items}]\n")).is_ok());
    }

    #[test]
    fn directives_are_refused_before_the_scanner_sees_them() {
        // This input makes saphyr-parser 0.0.12 allocate without bound.
        let bomb = "%\u{fffd}\u{fffd}&\u{fffd}`\u{fffd}s";
        let e = parse_yaml(bomb).unwrap_err();
        assert_eq!(e.loc, Loc { line: 1, col: 1 });
        assert!(e.message.contains("directive"), "{}", e.message);
        let e = parse_yaml("a: 1\n%YAML 1.2\n").unwrap_err();
        assert_eq!(e.loc, Loc { line: 2, col: 1 });
        assert!(parse_override(bomb).is_err());
        // `%` elsewhere is ordinary text.
        assert!(parse_yaml("a: \"50%\"\nb: x%y\n").is_ok());
    }

    #[test]
    fn clip_keeps_short_text_and_cuts_long_text_at_a_character() {
        assert_eq!(clip("abc"), "abc");
        let long = "é".repeat(1000);
        let c = clip(&long);
        assert!(c.starts_with(&"é".repeat(80)));
        assert!(c.ends_with("… (2000 bytes)"), "{c}");
    }

    #[test]
    fn duplicate_keys_are_errors_with_their_location() {
        let e = parse_yaml("a: 1\nb:\n  c: 1\n  c: 2\n").unwrap_err();
        assert_eq!(e.loc, Loc { line: 4, col: 3 });
        assert!(e.message.contains("`c` is given twice"), "{}", e.message);
        // Same key in different mappings, or as a value, is fine.
        assert!(parse_yaml("a: {x: 1}\nb: {x: 1}\nc: [a, a]\nd: a\n").is_ok());
    }

    #[test]
    fn syntax_errors_carry_a_location() {
        let e = parse_yaml("a: [1, 2\nb: 3\n").unwrap_err();
        assert!(e.loc.line >= 1, "{e:?}");
    }

    #[test]
    fn overrides_parse_as_yaml_scalars() {
        assert_eq!(parse_override("0.25").unwrap(), Value::Float(0.25));
        assert_eq!(parse_override("12").unwrap(), Value::Int(12));
        assert_eq!(
            parse_override("[1, 2]").unwrap(),
            Value::List(vec![Value::Int(1), Value::Int(2)])
        );
        assert!(parse_override("{a: 1}").is_err());
    }
}
