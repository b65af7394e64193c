//! Engine values and schemas ↔ protobuf messages.

use matflow_engine::node::{NodeInfo, ParamType, Params};
use matflow_engine::{CasRef, Digest, Value};

use crate::pb;

/// Bounds on what a request may carry, checked before anything else.
pub const MAX_PARAMS: usize = 256;
pub const MAX_STRING: usize = 4096;
pub const MAX_LIST: usize = 1024;

pub fn value_to_pb(v: &Value) -> pb::Value {
    use pb::value::Kind;
    let k = match v {
        Value::Null | Value::Map(_) => Kind::NullValue(true),
        Value::Bool(b) => Kind::BoolValue(*b),
        Value::Int(i) => Kind::IntValue(*i),
        Value::Float(f) => Kind::FloatValue(*f),
        Value::Str(s) => Kind::StringValue(s.clone()),
        Value::List(xs) => Kind::ListValue(pb::ValueList {
            items: xs.iter().map(value_to_pb).collect(),
        }),
    };
    pb::Value { kind: Some(k) }
}

/// A value from the wire; lists one level deep at most, bounded sizes.
pub fn value_from_pb(v: &pb::Value, depth: usize) -> Result<Value, crate::RpcError> {
    use crate::RpcError::Contract;
    use pb::value::Kind;
    Ok(match &v.kind {
        None | Some(Kind::NullValue(_)) => Value::Null,
        Some(Kind::BoolValue(b)) => Value::Bool(*b),
        Some(Kind::IntValue(i)) => Value::Int(*i),
        Some(Kind::FloatValue(f)) => {
            if !f.is_finite() {
                return Err(Contract(format!("{f} is not a finite number")));
            }
            Value::Float(*f)
        }
        Some(Kind::StringValue(s)) => {
            if s.len() > MAX_STRING {
                return Err(Contract(format!(
                    "a string of {} bytes (at most {MAX_STRING})",
                    s.len()
                )));
            }
            Value::Str(s.clone())
        }
        Some(Kind::ListValue(l)) => {
            if depth > 0 {
                return Err(Contract("lists inside lists".into()));
            }
            if l.items.len() > MAX_LIST {
                return Err(Contract(format!(
                    "a list of {} items (at most {MAX_LIST})",
                    l.items.len()
                )));
            }
            Value::List(
                l.items
                    .iter()
                    .map(|x| value_from_pb(x, depth + 1))
                    .collect::<Result<_, _>>()?,
            )
        }
    })
}

fn param_type(t: &ParamType) -> (pb::ParamType, f64, f64, u32, Vec<String>) {
    let strs = |c: &[&str]| c.iter().map(|s| s.to_string()).collect();
    match t {
        ParamType::Bool => (pb::ParamType::Bool, 0.0, 0.0, 0, vec![]),
        ParamType::Int { min, max } => (pb::ParamType::Int, *min as f64, *max as f64, 0, vec![]),
        ParamType::Float { min, max } => (pb::ParamType::Float, *min, *max, 0, vec![]),
        ParamType::Choice(c) => (pb::ParamType::Choice, 0.0, 0.0, 0, strs(c)),
        ParamType::InPath => (pb::ParamType::InPath, 0.0, 0.0, 0, vec![]),
        ParamType::OutPath => (pb::ParamType::OutPath, 0.0, 0.0, 0, vec![]),
        ParamType::Floats { len, min, max } => {
            (pb::ParamType::Floats, *min, *max, *len as u32, vec![])
        }
        ParamType::Ref(t) => (pb::ParamType::Ref, 0.0, 0.0, 0, strs(t)),
        ParamType::FloatOrFloats { len, min, max } => (
            pb::ParamType::FloatOrFloats,
            *min,
            *max,
            *len as u32,
            vec![],
        ),
        ParamType::Records { max, .. } => (pb::ParamType::Records, 0.0, 0.0, *max as u32, vec![]),
        ParamType::Record(_) => (pb::ParamType::Record, 0.0, 0.0, 0, vec![]),
    }
}

/// A node kind's [`NodeInfo`] as data.
pub fn node_kind(info: &NodeInfo) -> pb::NodeKind {
    pb::NodeKind {
        kind: info.kind.into(),
        version: info.version,
        doc: info.doc.into(),
        params: info
            .params
            .iter()
            .map(|p| {
                let (ty, min, max, len, choices) = param_type(&p.ty);
                pb::ParamSpec {
                    name: p.name.into(),
                    r#type: ty as i32,
                    min,
                    max,
                    len,
                    choices,
                    default_yaml: p.default.map(|d| d.to_string()),
                    unit: p.unit.into(),
                    doc: p.doc.into(),
                }
            })
            .collect(),
        outputs: info
            .outputs
            .iter()
            .map(|o| pb::OutputSpec {
                name: o.name.into(),
                r#type: o.ty.into(),
                doc: o.doc.into(),
            })
            .collect(),
    }
}

/// The parameters sent to a worker: output paths are the submitter's
/// business and go as null.
pub fn params_to_pb(
    info: &NodeInfo,
    params: &Params,
) -> std::collections::HashMap<String, pb::Value> {
    info.params
        .iter()
        .map(|p| {
            let v = match p.ty {
                ParamType::OutPath => Value::Null,
                _ => params.get(p.name).clone(),
            };
            (p.name.to_string(), value_to_pb(&v))
        })
        .collect()
}

pub fn blob_ref(d: &Digest, r: Option<&CasRef>) -> pb::BlobRef {
    pb::BlobRef {
        blake3: d.0.to_vec(),
        size_bytes: r.map(|r| r.size).unwrap_or(0),
        cas_hash: r.map(|r| r.hash.clone()).unwrap_or_default(),
    }
}

pub fn digest_from_bytes(b: &[u8]) -> Option<Digest> {
    <[u8; 32]>::try_from(b).ok().map(Digest)
}

/// A blob reference from the wire: its BLAKE3 digest and, when given,
/// where the store keeps it.
pub fn blob_from_pb(b: &pb::BlobRef) -> Result<(Digest, Option<CasRef>), String> {
    let d = digest_from_bytes(&b.blake3)
        .ok_or_else(|| format!("a blob digest of {} bytes (BLAKE3 has 32)", b.blake3.len()))?;
    if b.cas_hash.len() > 256 || !b.cas_hash.bytes().all(|c| c.is_ascii_hexdigit()) {
        return Err("a malformed store hash".into());
    }
    let r = (!b.cas_hash.is_empty()).then(|| CasRef {
        hash: b.cas_hash.clone(),
        size: b.size_bytes,
    });
    Ok((d, r))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_round_trip_and_are_bounded() {
        let vs = [
            Value::Null,
            Value::Bool(true),
            Value::Int(-7),
            Value::Float(0.25),
            Value::Str("gold".into()),
            Value::List(vec![Value::Float(1.0), Value::Int(2)]),
        ];
        for v in &vs {
            assert_eq!(&value_from_pb(&value_to_pb(v), 0).unwrap(), v);
        }
        let nested = value_to_pb(&Value::List(vec![Value::List(vec![])]));
        assert!(value_from_pb(&nested, 0).is_err());
        let long = value_to_pb(&Value::Str("x".repeat(MAX_STRING + 1)));
        assert!(value_from_pb(&long, 0).is_err());
        let nan = pb::Value {
            kind: Some(pb::value::Kind::FloatValue(f64::NAN)),
        };
        assert!(value_from_pb(&nan, 0).is_err());
    }
}
