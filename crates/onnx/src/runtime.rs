//! ONNX models through `ort`, with a backend that needs nothing fetched at
//! build time: `tract` (pure Rust, `ort-tract`; the default) or ONNX
//! Runtime's shared library loaded at run time (`onnxruntime`: faster),
//! found through `ORT_DYLIB_PATH` or the `onnxruntime` Python wheel.
//!
//! `ort` holds one API per process: the first model loaded fixes the
//! backend, and asking for the other one later is an error that says so.

use std::path::PathBuf;
use std::sync::{Mutex, OnceLock};

use ort::session::Session;
use ort::value::Tensor;

/// Which engine runs the models.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    Tract,
    OnnxRuntime,
}

impl Backend {
    pub const NAMES: &'static [&'static str] = &["tract", "onnxruntime"];
    pub fn name(self) -> &'static str {
        match self {
            Backend::Tract => "tract",
            Backend::OnnxRuntime => "onnxruntime",
        }
    }
    pub fn from_name(s: &str) -> Option<Backend> {
        match s {
            "tract" => Some(Backend::Tract),
            "onnxruntime" => Some(Backend::OnnxRuntime),
            _ => None,
        }
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OnnxError {
    #[error("{what}: not an ONNX model the {backend} backend can load: {message}")]
    Load {
        what: String,
        backend: &'static str,
        message: String,
    },
    #[error("{what}: expected {expected}, the model has {found}")]
    Signature {
        what: String,
        expected: String,
        found: String,
    },
    #[error("the onnxruntime backend: {0}")]
    Runtime(String),
    #[error(
        "this process already runs models on the {have} backend; {want} cannot be used beside it"
    )]
    Mixed {
        have: &'static str,
        want: &'static str,
    },
    #[error("{what}: running the model failed: {message}")]
    Run { what: String, message: String },
}

struct Env {
    backend: Backend,
    env: ort::environment::Environment,
}

static ENV: OnceLock<Result<Env, OnnxError>> = OnceLock::new();

/// The onnxruntime shared library: `ORT_DYLIB_PATH`, else the one inside
/// the `onnxruntime` Python wheel.
pub fn find_onnxruntime() -> Result<PathBuf, OnnxError> {
    if let Some(p) = std::env::var_os("ORT_DYLIB_PATH").filter(|v| !v.is_empty()) {
        let p = PathBuf::from(p);
        return if p.is_file() {
            Ok(p)
        } else {
            Err(OnnxError::Runtime(format!(
                "ORT_DYLIB_PATH={} is not a file",
                p.display()
            )))
        };
    }
    let out = std::process::Command::new("python3")
        .args([
            "-c",
            "import onnxruntime, os; print(os.path.join(os.path.dirname(onnxruntime.__file__), 'capi'))",
        ])
        .output()
        .map_err(|e| OnnxError::Runtime(format!("cannot run python3 to find onnxruntime: {e}")))?;
    if !out.status.success() {
        return Err(OnnxError::Runtime(
            "no ORT_DYLIB_PATH and no onnxruntime Python package (pip install onnxruntime)".into(),
        ));
    }
    let dir = PathBuf::from(String::from_utf8_lossy(&out.stdout).trim());
    let mut libs: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map_err(|e| OnnxError::Runtime(format!("{}: {e}", dir.display())))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("libonnxruntime.so"))
        })
        .collect();
    libs.sort();
    libs.pop().ok_or_else(|| {
        OnnxError::Runtime(format!(
            "{}: no libonnxruntime.so in the wheel",
            dir.display()
        ))
    })
}

fn environment(want: Backend) -> Result<&'static ort::environment::Environment, OnnxError> {
    let e = ENV.get_or_init(|| {
        let built = match want {
            Backend::Tract => {
                ort::set_api(ort_tract::api());
                ort::init()
                    .build()
                    .map_err(|e| OnnxError::Runtime(e.to_string()))
            }
            Backend::OnnxRuntime => {
                let lib = find_onnxruntime()?;
                // A missing or too old library panics inside ort: report it.
                let shown = lib.display().to_string();
                std::panic::catch_unwind(|| ort::init_from(&lib).map(|b| b.build()))
                    .map_err(|_| {
                        OnnxError::Runtime(format!(
                            "{shown}: could not be loaded (missing, or older than the API \
                             version 24 matflow needs: onnxruntime 1.24 or later)"
                        ))
                    })?
                    .map_err(|e| OnnxError::Runtime(format!("{shown}: {e}")))?
                    .map_err(|e| OnnxError::Runtime(format!("{shown}: {e}")))
            }
        };
        built.map(|env| Env { backend: want, env })
    });
    match e {
        Ok(env) if env.backend == want => Ok(&env.env),
        Ok(env) => Err(OnnxError::Mixed {
            have: env.backend.name(),
            want: want.name(),
        }),
        Err(e) => Err(e.clone()),
    }
}

fn shape_text(s: &[i64]) -> String {
    format!(
        "[{}]",
        s.iter()
            .map(|d| if *d < 0 { "N".into() } else { d.to_string() })
            .collect::<Vec<_>>()
            .join(", ")
    )
}

/// One input or output of a model: its name, element type and shape (a
/// negative dimension is dynamic).
#[derive(Clone, Debug, PartialEq)]
pub struct Port {
    pub name: String,
    pub f32: bool,
    pub elem: String,
    pub shape: Vec<i64>,
}

impl Port {
    /// `f32 [N, 3, 518, 518]`.
    pub fn describe(&self) -> String {
        format!(
            "{} {} {}",
            self.name,
            if self.f32 {
                "f32".into()
            } else {
                self.elem.clone()
            },
            shape_text(&self.shape)
        )
    }
}

/// One output of a run.
#[derive(Clone, Debug, PartialEq)]
pub struct Output {
    pub name: String,
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

/// A loaded model of any signature: its ports are read from the model.
pub struct Graph {
    what: String,
    backend: Backend,
    session: Mutex<Session>,
    pub inputs: Vec<Port>,
    pub outputs: Vec<Port>,
}

fn ports(outlets: &[ort::value::Outlet]) -> Vec<Port> {
    outlets
        .iter()
        .map(|o| {
            let t = o.dtype();
            let ty = t.tensor_type();
            Port {
                name: o.name().to_string(),
                f32: ty == Some(ort::value::TensorElementType::Float32),
                elem: match ty {
                    Some(ty) => format!("{ty:?}"),
                    None => "a non-tensor".into(),
                },
                shape: t
                    .tensor_shape()
                    .map(|s| s.iter().copied().collect())
                    .unwrap_or_default(),
            }
        })
        .collect()
}

/// Where a model comes from.
pub enum Source<'a> {
    Bytes(&'a [u8]),
    File(&'a std::path::Path),
}

impl Graph {
    /// Loads a model (`what` names it in errors).
    pub fn load(source: Source, what: &str, backend: Backend) -> Result<Graph, OnnxError> {
        let env = environment(backend)?;
        let load = |e: ort::Error| OnnxError::Load {
            what: what.to_string(),
            backend: backend.name(),
            message: e.to_string(),
        };
        let mut b = Session::builder(env).map_err(load)?;
        if backend == Backend::OnnxRuntime {
            b = b
                .with_deterministic_compute(true)
                .map_err(|e| load(e.into()))?
                .with_intra_threads(1)
                .map_err(|e| load(e.into()))?;
        }
        let session = match source {
            Source::Bytes(bytes) => b.commit_from_memory(bytes),
            Source::File(path) => b.commit_from_file(path),
        }
        .map_err(load)?;
        let inputs = ports(session.inputs());
        let outputs = ports(session.outputs());
        Ok(Graph {
            what: what.to_string(),
            backend,
            session: Mutex::new(session),
            inputs,
            outputs,
        })
    }

    pub fn what(&self) -> &str {
        &self.what
    }
    pub fn backend(&self) -> Backend {
        self.backend
    }

    /// Runs the model on one f32 input tensor of `shape`; returns every
    /// output (f32, all values finite) in the model's order.
    pub fn run(&self, shape: &[usize], x: Vec<f32>) -> Result<Vec<Output>, OnnxError> {
        let run = |m: String| OnnxError::Run {
            what: self.what.clone(),
            message: m,
        };
        if x.len() != shape.iter().product::<usize>() {
            return Err(run(format!(
                "{} input values for a tensor of shape {shape:?}",
                x.len()
            )));
        }
        let t = Tensor::from_array((shape.to_vec(), x)).map_err(|e| run(e.to_string()))?;
        let mut s = self
            .session
            .lock()
            .map_err(|_| run("an earlier run panicked".into()))?;
        let out = s.run(ort::inputs![t]).map_err(|e| run(e.to_string()))?;
        let mut all = Vec::with_capacity(self.outputs.len());
        for (i, port) in self.outputs.iter().enumerate() {
            let (shape, data) = out[i]
                .try_extract_tensor::<f32>()
                .map_err(|e| run(format!("output {}: {e}", port.name)))?;
            if let Some(j) = data.iter().position(|v| !v.is_finite()) {
                return Err(run(format!(
                    "output {} value {j} is {} (not finite)",
                    port.name, data[j]
                )));
            }
            all.push(Output {
                name: port.name.clone(),
                shape: shape.iter().map(|&d| d.max(0) as usize).collect(),
                data: data.to_vec(),
            });
        }
        Ok(all)
    }
}

/// A loaded model with one f32 input and one f32 output of fixed shapes
/// (but for the batch).
pub struct Model {
    graph: Graph,
    input: [usize; 3],
    output: [usize; 3],
}

impl Model {
    /// Loads `bytes` (`what` names the file in errors) and checks that it
    /// takes one f32 tensor [N, input…] and gives [N, output…].
    pub fn load(
        bytes: &[u8],
        what: &str,
        backend: Backend,
        input: [usize; 3],
        output: [usize; 3],
    ) -> Result<Model, OnnxError> {
        let graph = Graph::load(Source::Bytes(bytes), what, backend)?;
        let check = |kind: &str, ports: &[Port], want: [usize; 3]| {
            let expected = format!(
                "one {kind}: f32 {}",
                shape_text(&[-1, want[0] as i64, want[1] as i64, want[2] as i64])
            );
            let found = |s: String| OnnxError::Signature {
                what: what.to_string(),
                expected: expected.clone(),
                found: s,
            };
            if ports.len() != 1 {
                return Err(found(format!("{} {kind}s", ports.len())));
            }
            let p = &ports[0];
            let ok = p.f32
                && p.shape.len() == 4
                && p.shape[1..]
                    .iter()
                    .zip(want)
                    .all(|(&d, w)| d == w as i64 || d < 0);
            if ok {
                Ok(())
            } else {
                Err(found(format!("{} {}", p.elem, shape_text(&p.shape))))
            }
        };
        check("input", &graph.inputs, input)?;
        check("output", &graph.outputs, output)?;
        Ok(Model {
            graph,
            input,
            output,
        })
    }

    /// Runs a batch of `n` inputs (row-major [n, input…]); returns [n,
    /// output…].
    pub fn run(&self, n: usize, x: Vec<f32>) -> Result<Vec<f32>, OnnxError> {
        let [c, h, w] = self.input;
        let mut out = self.graph.run(&[n, c, h, w], x)?;
        let want = vec![n, self.output[0], self.output[1], self.output[2]];
        let o = out.swap_remove(0);
        if o.shape != want {
            return Err(OnnxError::Run {
                what: self.graph.what.clone(),
                message: format!("output shape {:?}, expected {want:?}", o.shape),
            });
        }
        Ok(o.data)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::refraction::{CROP, IN_CH, OUT_CH};
    use std::path::Path;

    fn repo(rel: &str) -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../..")
            .join(rel)
    }

    fn npy(rel: &str) -> matflow_scene::npy::Array {
        matflow_scene::npy::decode(&std::fs::read(repo(rel)).unwrap()).unwrap()
    }

    /// The shipped model gives, through tract, what PyTorch gave for the
    /// same held-out crop when it was exported (tolerance 1e-4 absolute;
    /// the outputs are lengths in units of the object's extent, about 0-2).
    #[test]
    fn the_shipped_model_matches_the_training_script() {
        let bytes = std::fs::read(repo("models/refraction_length.onnx")).unwrap();
        let m = Model::load(
            &bytes,
            "refraction_length.onnx",
            Backend::Tract,
            [IN_CH, CROP, CROP],
            [OUT_CH, CROP, CROP],
        )
        .unwrap();
        let x = npy("models/refraction_length.fixture_input.npy");
        let want = npy("models/refraction_length.fixture_output.npy");
        assert_eq!(x.shape, vec![1, IN_CH, CROP, CROP]);
        let got = m.run(1, x.values).unwrap();
        let worst = got
            .iter()
            .zip(&want.values)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        eprintln!("max |tract - torch| = {worst:e}");
        assert!(worst < 1e-4, "max |tract - torch| = {worst}");
        // An input of the wrong length is refused, not read past.
        assert!(m.run(1, vec![0.0; 5]).is_err());
    }

    #[test]
    fn corrupt_and_wrong_shaped_models_are_named_errors() {
        let e = Model::load(
            b"not a model",
            "m.onnx",
            Backend::Tract,
            [IN_CH, CROP, CROP],
            [OUT_CH, CROP, CROP],
        )
        .err()
        .unwrap()
        .to_string();
        assert!(
            e.starts_with("m.onnx: not an ONNX model the tract backend can load"),
            "{e}"
        );
        let bytes = std::fs::read(repo("tests/data/identity_3x8x8.onnx")).unwrap();
        let e = Model::load(
            &bytes,
            "id.onnx",
            Backend::Tract,
            [IN_CH, CROP, CROP],
            [OUT_CH, CROP, CROP],
        )
        .err()
        .unwrap()
        .to_string();
        assert!(
            e.contains("id.onnx: expected one input: f32 [N, 8, 64, 64], the model has Float32 [N, 3, 8, 8]"),
            "{e}"
        );
        // After tract, this process cannot switch to onnxruntime.
        let e = Model::load(
            &bytes,
            "id.onnx",
            Backend::OnnxRuntime,
            [3, 8, 8],
            [3, 8, 8],
        )
        .err()
        .unwrap();
        assert!(
            matches!(
                e,
                OnnxError::Mixed {
                    have: "tract",
                    want: "onnxruntime"
                }
            ),
            "{e}"
        );
    }
}
