//! Node keys: BLAKE3 over a canonical, length-prefixed encoding of the node
//! kind, its implementation version, its parameters (defaults filled,
//! numbers as canonical f64/i64, input files by content) and the digests of
//! its inputs' outputs. Two stages with equal keys compute equal bytes, so
//! the key addresses the action cache; an upstream stage that recomputes to
//! identical bytes leaves downstream keys unchanged (early cutoff).

use std::collections::BTreeMap;
use std::io::Read;
use std::path::Path;

use crate::node::{Node, ParamType, Params};
use crate::store::Digest;
use crate::value::Value;

/// The encoding's own version; changing the encoding changes every key.
const KEY_FORMAT: &[u8] = b"matflow-node-key/1";

struct Enc(blake3::Hasher);

impl Enc {
    fn new(domain: &[u8]) -> Enc {
        let mut e = Enc(blake3::Hasher::new());
        e.bytes(domain);
        e
    }
    fn bytes(&mut self, b: &[u8]) {
        self.0.update(&(b.len() as u64).to_le_bytes());
        self.0.update(b);
    }
    fn tag(&mut self, t: u8) {
        self.0.update(&[t]);
    }
    fn value(&mut self, v: &Value) {
        match v {
            Value::Null => self.tag(0),
            Value::Bool(b) => {
                self.tag(1);
                self.tag(*b as u8);
            }
            Value::Int(i) => {
                self.tag(2);
                self.0.update(&i.to_le_bytes());
            }
            Value::Float(x) => {
                self.tag(3);
                // -0 and 0 are the same parameter.
                let x = if *x == 0.0 { 0.0 } else { *x };
                self.0.update(&x.to_bits().to_le_bytes());
            }
            Value::Str(s) => {
                self.tag(4);
                self.bytes(s.as_bytes());
            }
            Value::List(xs) => {
                self.tag(5);
                self.0.update(&(xs.len() as u64).to_le_bytes());
                for x in xs {
                    self.value(x);
                }
            }
            Value::Map(m) => {
                self.tag(6);
                self.0.update(&(m.len() as u64).to_le_bytes());
                for (k, _, v, _) in m {
                    self.bytes(k.as_bytes());
                    self.value(v);
                }
            }
        }
    }
    fn finish(self) -> Digest {
        Digest(*self.0.finalize().as_bytes())
    }
}

/// BLAKE3 of a file's bytes, or of a folder's sorted (name, kind, digest)
/// entries, recursively.
pub fn path_digest(p: &Path) -> std::io::Result<Digest> {
    let meta = std::fs::metadata(p)?;
    if meta.is_dir() {
        let mut names: Vec<_> = std::fs::read_dir(p)?
            .map(|e| e.map(|e| e.file_name()))
            .collect::<Result<_, _>>()?;
        names.sort();
        let mut e = Enc::new(b"matflow-dir/1");
        for n in names {
            let d = path_digest(&p.join(&n))?;
            e.bytes(n.to_string_lossy().as_bytes());
            e.bytes(&d.0);
        }
        Ok(e.finish())
    } else {
        // Many stages may name one file (a dataset's thousands of samples
        // share a few envmaps): hash it once per process, again only when
        // its size or modification time changes.
        let stamp = (p.to_path_buf(), meta.len(), meta.modified().ok());
        let memo = FILE_DIGESTS.get_or_init(Default::default);
        if let Some(d) = memo.lock().ok().and_then(|m| m.get(&stamp).copied()) {
            return Ok(d);
        }
        let mut f = std::fs::File::open(p)?;
        let mut h = blake3::Hasher::new();
        let mut buf = vec![0u8; 1 << 16];
        loop {
            let n = f.read(&mut buf)?;
            if n == 0 {
                break;
            }
            h.update(&buf[..n]);
        }
        let d = Digest(*h.finalize().as_bytes());
        if let Ok(mut m) = memo.lock() {
            m.insert(stamp, d);
        }
        Ok(d)
    }
}

type FileStamp = (std::path::PathBuf, u64, Option<std::time::SystemTime>);

/// Digests of files already hashed by this process, by path, size and
/// modification time.
static FILE_DIGESTS: std::sync::OnceLock<
    std::sync::Mutex<std::collections::HashMap<FileStamp, Digest>>,
> = std::sync::OnceLock::new();

fn params_part(e: &mut Enc, node: &dyn Node, params: &Params) -> std::io::Result<()> {
    for p in node.params() {
        let v = params.get(p.name);
        match p.ty {
            // Where results are written does not change them.
            ParamType::OutPath => continue,
            // References enter through the input digests.
            ParamType::Ref(_) => continue,
            _ => {
                e.bytes(p.name.as_bytes());
                param_value(e, &p.ty, v)?;
            }
        }
    }
    Ok(())
}

/// A parameter's value in the key: input files by their contents, here
/// and in records' fields; everything else as written.
fn param_value(e: &mut Enc, ty: &ParamType, v: &Value) -> std::io::Result<()> {
    encode_param(e, ty, v, &|e, path| {
        e.tag(7);
        e.bytes(&path_digest(Path::new(path))?.0);
        Ok(())
    })
}

/// A parameter's value as written, records field by field, each input
/// file (here or in a record) encoded by `file`.
fn encode_param(
    e: &mut Enc,
    ty: &ParamType,
    v: &Value,
    file: &dyn Fn(&mut Enc, &str) -> std::io::Result<()>,
) -> std::io::Result<()> {
    match (ty, v) {
        (ParamType::InPath, Value::Str(s)) => file(e, s)?,
        (ParamType::Records { fields, .. }, Value::List(items)) => {
            e.tag(5);
            e.0.update(&(items.len() as u64).to_le_bytes());
            for item in items {
                encode_param(e, &ParamType::Record(fields), item, file)?;
            }
        }
        (ParamType::Record(fields), Value::Map(m)) => {
            e.tag(6);
            e.0.update(&(m.len() as u64).to_le_bytes());
            for (k, _, fv, _) in m {
                e.bytes(k.as_bytes());
                match fields.iter().find(|f| f.name == k) {
                    Some(f) => encode_param(e, &f.ty, fv, file)?,
                    None => e.value(fv),
                }
            }
        }
        _ => e.value(v),
    }
    Ok(())
}

/// The node key of a stage.
pub fn node_key(
    node: &dyn Node,
    params: &Params,
    inputs: &BTreeMap<String, Digest>,
) -> std::io::Result<Digest> {
    let mut e = Enc::new(KEY_FORMAT);
    e.bytes(node.kind().as_bytes());
    e.0.update(&node.version().to_le_bytes());
    params_part(&mut e, node, params)?;
    e.0.update(&(inputs.len() as u64).to_le_bytes());
    for (name, d) in inputs {
        e.bytes(name.as_bytes());
        e.bytes(&d.0);
    }
    Ok(e.finish())
}

/// The stage's random seed: from its kind and parameters, not its inputs,
/// so an upstream edit keeps the noise pattern. An input file enters by
/// whether it is given, not by its path or its contents: its contents are
/// an input like any other (a new version keeps the noise), and its path
/// is how the pipeline spells it, which the key does not see (two
/// spellings of one file are one action and must compute one result).
pub fn node_seed(node: &dyn Node, params: &Params) -> u64 {
    let mut e = Enc::new(b"matflow-seed/1");
    e.bytes(node.kind().as_bytes());
    for p in node.params() {
        if matches!(p.ty, ParamType::OutPath | ParamType::Ref(_)) {
            continue;
        }
        e.bytes(p.name.as_bytes());
        seed_value(&mut e, &p.ty, params.get(p.name));
    }
    let d = e.finish();
    u64::from_le_bytes(d.0[..8].try_into().unwrap())
}

/// A parameter's value in the seed: as in the key, but an input file (here
/// or in records' fields) only as given.
fn seed_value(e: &mut Enc, ty: &ParamType, v: &Value) {
    // Nothing here reads a file, so nothing fails.
    let _ = encode_param(e, ty, v, &|e, _| {
        e.tag(7);
        Ok(())
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_is_hashed_again_when_it_changes() {
        let d = tempfile::tempdir().unwrap();
        let f = d.path().join("x.bin");
        std::fs::write(&f, b"one").unwrap();
        let a = path_digest(&f).unwrap();
        assert_eq!(a, Digest::of(b"one"));
        assert_eq!(path_digest(&f).unwrap(), a, "the memo answers alike");
        std::fs::write(&f, b"three").unwrap();
        assert_eq!(path_digest(&f).unwrap(), Digest::of(b"three"));
        // Same size, later time: hashed again.
        std::thread::sleep(std::time::Duration::from_millis(20));
        std::fs::write(&f, b"thrie").unwrap();
        assert_eq!(path_digest(&f).unwrap(), Digest::of(b"thrie"));
    }

    #[test]
    fn encoding_is_length_prefixed_and_canonical() {
        let h = |vs: &[Value]| {
            let mut e = Enc::new(b"t");
            for v in vs {
                e.value(v);
            }
            e.finish()
        };
        // Concatenations that would collide without length prefixes.
        assert_ne!(
            h(&[Value::Str("ab".into()), Value::Str("c".into())]),
            h(&[Value::Str("a".into()), Value::Str("bc".into())])
        );
        assert_eq!(h(&[Value::Float(-0.0)]), h(&[Value::Float(0.0)]));
        assert_ne!(h(&[Value::Float(1.0)]), h(&[Value::Int(1)]));
        assert_ne!(
            h(&[Value::List(vec![Value::Int(1)]), Value::Int(2)]),
            h(&[Value::List(vec![Value::Int(1), Value::Int(2)])])
        );
    }

    #[test]
    fn folder_digest_follows_content_not_time() {
        let d = tempfile::tempdir().unwrap();
        std::fs::write(d.path().join("a"), b"1").unwrap();
        std::fs::create_dir(d.path().join("s")).unwrap();
        std::fs::write(d.path().join("s/b"), b"2").unwrap();
        let x = path_digest(d.path()).unwrap();
        std::fs::write(d.path().join("s/b"), b"2").unwrap();
        assert_eq!(x, path_digest(d.path()).unwrap());
        std::fs::write(d.path().join("s/b"), b"3").unwrap();
        assert_ne!(x, path_digest(d.path()).unwrap());
    }
}
