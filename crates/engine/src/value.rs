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

/// Finds a key given twice in one mapping (YAML forbids it; the loader
/// would keep the last silently, hiding a stage or a parameter).
struct DuplicateKeys {
    /// Per open container: for mappings, the keys seen and whether the
    /// next node is a key.
    stack: Vec<Option<(std::collections::BTreeSet<String>, bool)>>,
    found: Option<ParseError>,
}

impl DuplicateKeys {
    /// A node starts in the innermost container; returns true if it is a
    /// mapping key.
    fn node(&mut self) -> bool {
        match self.stack.last_mut() {
            Some(Some((_, expect_key))) => {
                let k = *expect_key;
                *expect_key = !k;
                k
            }
            _ => false,
        }
    }
}

impl<'i> saphyr_parser::SpannedEventReceiver<'i> for DuplicateKeys {
    fn on_event(&mut self, ev: saphyr_parser::Event<'i>, span: saphyr_parser::Span) {
        use saphyr_parser::Event;
        match ev {
            // The guard also advances the key/value alternation.
            Event::Scalar(v, ..) if self.node() => {
                if let Some(Some((keys, _))) = self.stack.last_mut() {
                    if !keys.insert(v.to_string()) && self.found.is_none() {
                        self.found = Some(ParseError {
                            loc: Loc {
                                line: span.start.line(),
                                col: span.start.col() + 1,
                            },
                            message: format!("`{v}` is given twice in this mapping"),
                        });
                    }
                }
            }
            Event::Alias(_) => {
                self.node();
            }
            Event::SequenceStart(..) => {
                self.node();
                self.stack.push(None);
            }
            Event::MappingStart(..) => {
                self.node();
                self.stack.push(Some((Default::default(), true)));
            }
            Event::SequenceEnd | Event::MappingEnd => {
                self.stack.pop();
            }
            _ => {}
        }
    }
}

/// Parses one YAML document into a located value tree. A key given twice
/// in one mapping is an error.
pub fn parse_yaml(text: &str) -> Result<(Value, Loc), ParseError> {
    let mut dup = DuplicateKeys {
        stack: Vec::new(),
        found: None,
    };
    // Syntax errors are reported by the loader below, with its message.
    if saphyr_parser::Parser::new_from_str(text)
        .load(&mut dup, true)
        .is_ok()
    {
        if let Some(e) = dup.found {
            return Err(e);
        }
    }
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
        Ok((Value::Map(_), _)) => Err(format!("'{text}' is a mapping; give a scalar or a list")),
        Ok((v, _)) => Ok(v),
        Err(e) => Err(format!("'{text}': {}", e.message)),
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
