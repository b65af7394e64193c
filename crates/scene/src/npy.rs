//! NumPy `.npy` arrays (format version 1.0), the members a dataset's
//! float maps are stored as: `numpy.load`, PyTorch and the `webdataset`
//! decoder read them without extra libraries. Little endian, C order.

use half::f16;

/// An element type a `.npy` array may hold here.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dtype {
    /// `<f2`: half precision (labels: 11 significant bits).
    F16,
    /// `<f4`.
    F32,
    /// `|u1`.
    U8,
}

impl Dtype {
    fn descr(self) -> &'static str {
        match self {
            Dtype::F16 => "<f2",
            Dtype::F32 => "<f4",
            Dtype::U8 => "|u1",
        }
    }
    fn size(self) -> usize {
        match self {
            Dtype::F16 => 2,
            Dtype::F32 => 4,
            Dtype::U8 => 1,
        }
    }
}

fn header(dtype: Dtype, shape: &[usize]) -> Vec<u8> {
    let dims = match shape {
        [n] => format!("({n},)"),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut dict = format!(
        "{{'descr': '{}', 'fortran_order': False, 'shape': {dims}, }}",
        dtype.descr()
    );
    // Magic (6) + version (2) + length (2) + dict + '\n', padded to 64.
    while (10 + dict.len() + 1) % 64 != 0 {
        dict.push(' ');
    }
    dict.push('\n');
    let mut out = Vec::with_capacity(10 + dict.len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out
}

/// `values` (row-major, `shape`'s product long) as a `.npy` file of
/// `dtype` (rounded to nearest for f16; clamped and rounded for u8).
pub fn encode(values: &[f32], shape: &[usize], dtype: Dtype) -> Vec<u8> {
    debug_assert_eq!(values.len(), shape.iter().product::<usize>());
    let mut out = header(dtype, shape);
    out.reserve(values.len() * dtype.size());
    for &v in values {
        match dtype {
            Dtype::F16 => out.extend_from_slice(&f16::from_f32(v).to_le_bytes()),
            Dtype::F32 => out.extend_from_slice(&v.to_le_bytes()),
            Dtype::U8 => out.push(if v.is_finite() {
                v.round().clamp(0.0, 255.0) as u8
            } else {
                0
            }),
        }
    }
    out
}

/// A decoded array: its shape and its values as f32.
#[derive(Clone, Debug, PartialEq)]
pub struct Array {
    pub shape: Vec<usize>,
    pub dtype: Dtype,
    pub values: Vec<f32>,
}

/// Reads a `.npy` array of one of [`Dtype`]'s types (C order, version 1
/// or 2); the message says what is wrong.
pub fn decode(bytes: &[u8]) -> Result<Array, String> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err("not a .npy file (no \\x93NUMPY magic)".into());
    }
    let (hlen, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        v => return Err(format!(".npy format version {v} is not supported")),
    };
    let dict = bytes
        .get(start..start + hlen)
        .and_then(|h| std::str::from_utf8(h).ok())
        .ok_or("the .npy header is cut short or not text")?;
    let field = |name: &str| -> Option<&str> {
        let at = dict.find(&format!("'{name}':"))? + name.len() + 3;
        Some(dict[at..].trim_start())
    };
    let descr = field("descr").ok_or("the .npy header has no descr")?;
    let dtype = if descr.starts_with("'<f2'") {
        Dtype::F16
    } else if descr.starts_with("'<f4'") {
        Dtype::F32
    } else if descr.starts_with("'|u1'") {
        Dtype::U8
    } else {
        return Err(format!(
            "the .npy element type {} is not f16, f32 or u8",
            descr.split(',').next().unwrap_or("")
        ));
    };
    if field("fortran_order").is_some_and(|f| f.starts_with("True")) {
        return Err("Fortran-ordered .npy arrays are not supported".into());
    }
    let shape_text = field("shape").ok_or("the .npy header has no shape")?;
    let close = shape_text
        .find(')')
        .ok_or("the .npy shape is not a tuple")?;
    let shape: Vec<usize> = shape_text[1..close]
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>())
        .collect::<Result<_, _>>()
        .map_err(|_| "the .npy shape is not a tuple of sizes".to_string())?;
    let n = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .ok_or("the .npy shape overflows")?;
    let data = &bytes[start + hlen..];
    if Some(data.len()) != n.checked_mul(dtype.size()) {
        return Err(format!(
            "the .npy data holds {} bytes, its shape {shape:?} needs {}",
            data.len(),
            n.saturating_mul(dtype.size())
        ));
    }
    let values = match dtype {
        Dtype::F16 => data
            .chunks_exact(2)
            .map(|c| f16::from_le_bytes([c[0], c[1]]).to_f32())
            .collect(),
        Dtype::F32 => data
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect(),
        Dtype::U8 => data.iter().map(|&b| b as f32).collect(),
    };
    Ok(Array {
        shape,
        dtype,
        values,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arrays_round_trip_with_aligned_headers() {
        let v: Vec<f32> = (0..24).map(|k| k as f32 * 0.37 - 3.0).collect();
        for (dtype, tol) in [(Dtype::F32, 0.0), (Dtype::F16, 4e-3), (Dtype::U8, 0.0)] {
            let vals: Vec<f32> = if dtype == Dtype::U8 {
                v.iter().map(|x| (x * 10.0).abs().round()).collect()
            } else {
                v.clone()
            };
            for shape in [vec![24], vec![4, 6], vec![2, 4, 3]] {
                let b = encode(&vals, &shape, dtype);
                let hl = u16::from_le_bytes([b[8], b[9]]) as usize;
                assert_eq!((10 + hl) % 64, 0, "header not aligned");
                let a = decode(&b).unwrap();
                assert_eq!((a.shape.clone(), a.dtype), (shape, dtype));
                for (x, y) in a.values.iter().zip(&vals) {
                    assert!((x - y).abs() <= tol * y.abs().max(1.0), "{x} vs {y}");
                }
            }
        }
        assert!(decode(b"NUMPY").is_err());
        let mut cut = encode(&v, &[24], Dtype::F32);
        cut.pop();
        assert!(decode(&cut).unwrap_err().contains("needs 96"));
    }
}
