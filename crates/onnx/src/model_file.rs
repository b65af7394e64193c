//! What matflow reads from an ONNX file besides its graph: the producer,
//! the `metadata_props` (key → value; matflow's keys start `matflow.`), its
//! BLAKE3 digest and size — and whether the machine has the memory to run
//! it.
//!
//! The metadata is read by walking the top level of the `ModelProto`
//! message (protobuf wire format) and skipping everything else, so a model
//! of any size is scanned without loading it, whichever backend runs it.

use std::collections::BTreeMap;
use std::io::{Read, Seek, SeekFrom};

/// ModelProto's field numbers that matter here.
const PRODUCER_NAME: u64 = 2;
const METADATA_PROPS: u64 = 14;

#[derive(Clone, Debug, Default, PartialEq)]
pub struct ModelInfo {
    /// File size in bytes.
    pub bytes: u64,
    /// BLAKE3 of the file, hex.
    pub blake3: String,
    pub producer: String,
    pub metadata: BTreeMap<String, String>,
}

#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct ScanError(pub String);

fn varint(r: &mut impl Read) -> Result<Option<u64>, ScanError> {
    let mut v = 0u64;
    for i in 0..10 {
        let mut b = [0u8];
        match r.read(&mut b) {
            Ok(0) if i == 0 => return Ok(None),
            Ok(0) => return Err(ScanError("the file ends inside a varint".into())),
            Ok(_) => {}
            Err(e) => return Err(ScanError(e.to_string())),
        }
        v |= ((b[0] & 0x7f) as u64) << (7 * i);
        if b[0] & 0x80 == 0 {
            return Ok(Some(v));
        }
    }
    Err(ScanError("a varint longer than 10 bytes".into()))
}

/// The string fields 1 (key) and 2 (value) of a StringStringEntryProto.
fn entry(b: &[u8]) -> Result<(String, String), ScanError> {
    let mut r = b;
    let (mut k, mut v) = (String::new(), String::new());
    while let Some(tag) = varint(&mut r)? {
        let (field, wire) = (tag >> 3, tag & 7);
        if wire != 2 {
            return Err(ScanError(format!(
                "metadata entry field {field} has wire type {wire}"
            )));
        }
        let n = varint(&mut r)?.ok_or_else(|| ScanError("truncated metadata entry".into()))?;
        if n as usize > r.len() {
            return Err(ScanError("truncated metadata entry".into()));
        }
        let (s, rest) = r.split_at(n as usize);
        let s = String::from_utf8_lossy(s).into_owned();
        match field {
            1 => k = s,
            2 => v = s,
            _ => {}
        }
        r = rest;
    }
    Ok((k, v))
}

/// Producer and metadata of the ModelProto in `r` (positioned at its
/// start; `len` its length in bytes).
pub fn scan(
    r: &mut (impl Read + Seek),
    len: u64,
) -> Result<(String, BTreeMap<String, String>), ScanError> {
    let mut producer = String::new();
    let mut meta = BTreeMap::new();
    let mut pos = 0u64;
    let mut fields = 0usize;
    while pos < len {
        let Some(tag) = varint(r)? else { break };
        let (field, wire) = (tag >> 3, tag & 7);
        if field == 0 {
            return Err(ScanError("field number 0: not a protobuf message".into()));
        }
        fields += 1;
        match wire {
            0 => {
                varint(r)?.ok_or_else(|| ScanError("truncated varint field".into()))?;
            }
            1 => {
                r.seek(SeekFrom::Current(8))
                    .map_err(|e| ScanError(e.to_string()))?;
            }
            5 => {
                r.seek(SeekFrom::Current(4))
                    .map_err(|e| ScanError(e.to_string()))?;
            }
            2 => {
                let n = varint(r)?.ok_or_else(|| ScanError("truncated length".into()))?;
                let here = r.stream_position().map_err(|e| ScanError(e.to_string()))?;
                if here + n > len {
                    return Err(ScanError(format!(
                        "field {field} runs {} bytes past the end of the file (truncated?)",
                        here + n - len
                    )));
                }
                if field == PRODUCER_NAME || field == METADATA_PROPS {
                    if n > 1 << 20 {
                        return Err(ScanError(format!("a {n}-byte metadata field")));
                    }
                    let mut b = vec![0u8; n as usize];
                    r.read_exact(&mut b).map_err(|e| ScanError(e.to_string()))?;
                    if field == PRODUCER_NAME {
                        producer = String::from_utf8_lossy(&b).into_owned();
                    } else {
                        let (k, v) = entry(&b)?;
                        meta.insert(k, v);
                    }
                } else {
                    r.seek(SeekFrom::Current(n as i64))
                        .map_err(|e| ScanError(e.to_string()))?;
                }
            }
            w => {
                return Err(ScanError(format!(
                    "wire type {w} (field {field}): not an ONNX model"
                )))
            }
        }
        pos = r.stream_position().map_err(|e| ScanError(e.to_string()))?;
    }
    if pos > len {
        return Err(ScanError(
            "the last field runs past the end (truncated?)".into(),
        ));
    }
    if fields == 0 {
        return Err(ScanError("an empty file".into()));
    }
    Ok((producer, meta))
}

/// [`ModelInfo`] of a model held in memory.
pub fn info_of_bytes(b: &[u8]) -> Result<ModelInfo, ScanError> {
    let (producer, metadata) = scan(&mut std::io::Cursor::new(b), b.len() as u64)?;
    Ok(ModelInfo {
        bytes: b.len() as u64,
        blake3: blake3::hash(b).to_hex().to_string(),
        producer,
        metadata,
    })
}

/// [`ModelInfo`] of a model file, read in a streaming pass (digest) and a
/// seeking one (metadata).
pub fn info_of_file(path: &std::path::Path) -> Result<ModelInfo, ScanError> {
    let io = |e: std::io::Error| ScanError(e.to_string());
    let mut f = std::fs::File::open(path).map_err(io)?;
    let len = f.metadata().map_err(io)?.len();
    let mut h = blake3::Hasher::new();
    h.update_reader(&mut f).map_err(io)?;
    f.seek(SeekFrom::Start(0)).map_err(io)?;
    let mut r = std::io::BufReader::new(f);
    let (producer, metadata) = scan(&mut r, len)?;
    Ok(ModelInfo {
        bytes: len,
        blake3: h.finalize().to_hex().to_string(),
        producer,
        metadata,
    })
}

/// Bytes of memory this process may still take: the smaller of the
/// kernel's `MemAvailable` and what the cgroup's `memory.max` leaves
/// (None when neither can be read).
pub fn memory_available() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok().and_then(|s| {
        s.lines()
            .find(|l| l.starts_with("MemAvailable:"))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|kb| kb.parse::<u64>().ok())
            .map(|kb| kb * 1024)
    });
    let read = |p: &str| {
        std::fs::read_to_string(p)
            .ok()
            .and_then(|s| s.trim().parse::<u64>().ok())
    };
    let cgroup = match (
        read("/sys/fs/cgroup/memory.max"),
        read("/sys/fs/cgroup/memory.current"),
    ) {
        (Some(max), Some(cur)) => Some(max.saturating_sub(cur)),
        _ => None,
    };
    match (meminfo, cgroup) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    }
}

/// What running a model of `model_bytes` on one image of `input_values`
/// floats is expected to need: the weights about three times over (the
/// file, the runtime's copy, its optimised plan) plus activations of a
/// hundred copies of the input, plus a fixed margin.
pub fn memory_needed(model_bytes: u64, input_values: u64) -> u64 {
    3 * model_bytes + 4 * 100 * input_values + (256 << 20)
}

/// Err with a message when `needed` exceeds `available`.
pub fn check_memory(what: &str, needed: u64, available: Option<u64>) -> Result<(), String> {
    match available {
        Some(a) if needed > a => Err(format!(
            "{what}: running it needs about {:.2} GB of memory and {:.2} GB is available; \
             free memory, or use a smaller model",
            needed as f64 / 1e9,
            a as f64 / 1e9
        )),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field_bytes(field: u64, payload: &[u8]) -> Vec<u8> {
        let mut out = vec![];
        let mut put = |mut v: u64| loop {
            let b = (v & 0x7f) as u8;
            v >>= 7;
            if v == 0 {
                out.push(b);
                break;
            }
            out.push(b | 0x80);
        };
        put(field << 3 | 2);
        put(payload.len() as u64);
        out.extend_from_slice(payload);
        out
    }

    #[test]
    fn reads_producer_and_metadata_and_refuses_truncation() {
        let mut m = vec![0x08, 0x08]; // ir_version = 8
        m.extend(field_bytes(2, b"pytorch"));
        m.extend(field_bytes(7, &[0u8; 300])); // a "graph", skipped
        let mut e = field_bytes(1, b"matflow.depth");
        e.extend(field_bytes(2, b"z"));
        m.extend(field_bytes(14, &e));
        let info = info_of_bytes(&m).unwrap();
        assert_eq!(info.producer, "pytorch");
        assert_eq!(
            info.metadata.get("matflow.depth").map(|s| s.as_str()),
            Some("z")
        );
        assert_eq!(info.bytes, m.len() as u64);
        let e = info_of_bytes(&m[..100]).unwrap_err().to_string();
        assert!(e.contains("past the end"), "{e}");
        assert!(info_of_bytes(b"").is_err());
        assert!(info_of_bytes(b"\x07garbage").is_err());
    }

    #[test]
    fn memory_rule() {
        assert!(check_memory("m.onnx", 2_000_000_000, Some(1_000_000_000))
            .unwrap_err()
            .contains("m.onnx: running it needs about 2.00 GB of memory and 1.00 GB is available"));
        assert!(check_memory("m", 10, Some(11)).is_ok());
        assert!(check_memory("m", 10, None).is_ok());
        // The 430 MB MatNet export at 518² needs about 1.7 GB, as measured
        // (≈ 1.65 GB peak under onnxruntime).
        let need = memory_needed(430_000_000, 3 * 518 * 518);
        assert!((1.4e9..2.2e9).contains(&(need as f64)), "{need}");
    }
}
