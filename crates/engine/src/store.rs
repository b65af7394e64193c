//! The content-addressed store: blobs addressed by the BLAKE3 hash of their
//! bytes, and the action cache mapping a node key to its output digests.
//!
//! Layout under the root: `blobs/ab/cdef…` (the hex digest split after two
//! characters), `actions/ab/cdef….json`, `tmp/`. Every write goes to
//! `tmp/` first and is renamed into place, so a reader sees a whole file
//! or none. Every blob read is re-hashed: a corrupt blob is deleted and
//! reported as missing (a cache miss, never a wrong result), and an action
//! is served only if all its blobs are present.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, SystemTime};

#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Digest(pub [u8; 32]);

impl Digest {
    /// BLAKE3 of `bytes` (large inputs hashed on all cores; the digest
    /// does not depend on how).
    pub fn of(bytes: &[u8]) -> Digest {
        if bytes.len() >= 1 << 20 {
            let mut h = blake3::Hasher::new();
            h.update_rayon(bytes);
            Digest(*h.finalize().as_bytes())
        } else {
            Digest(*blake3::hash(bytes).as_bytes())
        }
    }
    pub fn hex(&self) -> String {
        self.0.iter().map(|b| format!("{b:02x}")).collect()
    }
    pub fn from_hex(s: &str) -> Option<Digest> {
        if s.len() != 64 {
            return None;
        }
        let mut out = [0u8; 32];
        for (i, o) in out.iter_mut().enumerate() {
            *o = u8::from_str_radix(s.get(2 * i..2 * i + 2)?, 16).ok()?;
        }
        Some(Digest(out))
    }
}

impl fmt::Display for Digest {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.hex())
    }
}

impl fmt::Debug for Digest {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Digest({})", &self.hex()[..12])
    }
}

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("cache {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A remote tier could not be reached or answered with an error.
    #[error("remote cache {endpoint}: {message}")]
    Remote { endpoint: String, message: String },
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// One action-cache entry: what a node key computed.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct Action {
    pub kind: String,
    /// The stage that computed it (informational; keys are what match).
    pub stage: String,
    pub pipeline: String,
    /// Output name → blob digest (hex).
    pub outputs: BTreeMap<String, String>,
    pub seconds: f64,
    /// Where it ran (`local`, or a worker's address); informational.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub worker: String,
}

impl Action {
    pub fn digests(&self) -> Option<BTreeMap<String, Digest>> {
        self.outputs
            .iter()
            .map(|(k, v)| Digest::from_hex(v).map(|d| (k.clone(), d)))
            .collect()
    }
}

pub struct Store {
    root: PathBuf,
    counter: AtomicU64,
}

/// Totals for `matflow cache stats`.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Stats {
    pub blobs: u64,
    pub blob_bytes: u64,
    pub actions: u64,
    pub temp_files: u64,
}

/// What `verify` found, and what it removed: every count is of what
/// happened; a removal that failed is listed in `errors`, not counted.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct VerifyReport {
    pub blobs_ok: u64,
    pub blobs_corrupt: Vec<String>,
    pub actions_ok: u64,
    pub actions_unreadable: Vec<String>,
    pub actions_incomplete: Vec<String>,
    /// Entries whose outputs do not decode as the types their node
    /// declares (key: why).
    pub actions_wrong_type: Vec<String>,
    pub blobs_removed: u64,
    pub actions_removed: u64,
    /// What could not be read or removed (path: error).
    pub errors: Vec<String>,
}

/// What `gc` removed (only what was removed), and what it could not.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct GcReport {
    pub actions_removed: u64,
    pub blobs_removed: u64,
    pub bytes_freed: u64,
    pub temp_removed: u64,
    /// Entries kept because they belong to a kept pipeline's stage whose
    /// key could not be worked out (downstream of a missing entry).
    pub actions_kept_unresolved: u64,
    /// What could not be removed (path: error).
    pub errors: Vec<String>,
}

/// Which action entries `gc` keeps.
#[derive(Clone, Debug, Default)]
pub struct GcPolicy {
    /// Keep only these action keys (those the given pipelines reference);
    /// `None`: no such restriction.
    pub keep: Option<BTreeSet<Digest>>,
    /// Remove entries not used for this long.
    pub older_than: Option<Duration>,
    /// Remove least recently used entries until blobs total at most this.
    pub max_bytes: Option<u64>,
    /// With `keep`: entries of these (pipeline, stage) pairs are kept too.
    /// They are the stages whose keys could not be worked out because an
    /// entry upstream is missing or damaged; without this, one damaged
    /// entry would make `gc --keep` delete every intact one below it.
    pub keep_stages: BTreeSet<(String, String)>,
}

/// Bytes of each output blob [`Store::verify_with`] passes to its check.
pub const CHECK_HEAD: u64 = 64 << 10;

/// The first `n` bytes of a file (fewer if it is shorter or unreadable).
fn head(path: &Path, n: u64) -> Vec<u8> {
    use std::io::Read;
    let mut out = Vec::new();
    if let Ok(f) = std::fs::File::open(path) {
        let _ = f.take(n).read_to_end(&mut out);
    }
    out
}

/// Removes a file; `Ok(false)` if it was already gone.
fn remove(path: &Path) -> Result<bool, StoreError> {
    match std::fs::remove_file(path) {
        Ok(()) => Ok(true),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
        Err(e) => Err(io_err(path)(e)),
    }
}

/// This machine's name (for temporary files in a store that several
/// hosts share), read once.
fn host_name() -> &'static str {
    static HOST: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    HOST.get_or_init(|| {
        std::fs::read_to_string("/proc/sys/kernel/hostname")
            .ok()
            .or_else(|| std::env::var("HOSTNAME").ok())
            .map(|h| {
                h.trim()
                    .chars()
                    .filter(|c| c.is_ascii_alphanumeric() || *c == '-')
                    .take(32)
                    .collect::<String>()
            })
            .filter(|h| !h.is_empty())
            .unwrap_or_else(|| "host".into())
    })
}

/// One file of a [`Store::put_written`] record.
#[derive(serde::Serialize, serde::Deserialize)]
struct Written {
    path: PathBuf,
    size: u64,
    blake3: String,
}

impl Store {
    pub fn open(root: impl Into<PathBuf>) -> Result<Store, StoreError> {
        let root = root.into();
        for sub in ["blobs", "actions", "tmp"] {
            let p = root.join(sub);
            std::fs::create_dir_all(&p).map_err(io_err(&p))?;
        }
        Ok(Store {
            root,
            counter: AtomicU64::new(0),
        })
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn blob_path(&self, d: &Digest) -> PathBuf {
        let h = d.hex();
        self.root.join("blobs").join(&h[..2]).join(&h[2..])
    }

    pub fn action_path(&self, key: &Digest) -> PathBuf {
        let h = key.hex();
        self.root
            .join("actions")
            .join(&h[..2])
            .join(format!("{}.json", &h[2..]))
    }

    fn write_atomic(&self, dest: &Path, bytes: &[u8]) -> Result<(), StoreError> {
        let n = self.counter.fetch_add(1, Ordering::Relaxed);
        let nanos = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0);
        let tmp = self.root.join("tmp").join(format!(
            "{}-{}-{n}-{nanos}",
            host_name(),
            std::process::id()
        ));
        let res = (|| {
            let mut f = std::fs::File::create(&tmp)?;
            f.write_all(bytes)?;
            f.sync_all()?;
            if let Some(parent) = dest.parent() {
                std::fs::create_dir_all(parent)?;
            }
            std::fs::rename(&tmp, dest)
        })();
        if res.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        res.map_err(io_err(dest))
    }

    /// Stores bytes; returns their digest.
    pub fn put_blob(&self, bytes: &[u8]) -> Result<Digest, StoreError> {
        let d = Digest::of(bytes);
        let p = self.blob_path(&d);
        let whole = std::fs::metadata(&p)
            .map(|m| m.len() == bytes.len() as u64)
            .unwrap_or(false);
        if !whole {
            self.write_atomic(&p, bytes)?;
        }
        Ok(d)
    }

    /// The blob's bytes if present and intact. A blob whose bytes no longer
    /// hash to its name is deleted and reported as absent.
    pub fn get_blob(&self, d: &Digest) -> Result<Option<Vec<u8>>, StoreError> {
        let p = self.blob_path(d);
        let bytes = match std::fs::read(&p) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(io_err(&p)(e)),
        };
        if Digest::of(&bytes) != *d {
            let _ = std::fs::remove_file(&p);
            return Ok(None);
        }
        Ok(Some(bytes))
    }

    pub fn has_blob(&self, d: &Digest) -> bool {
        self.blob_path(d).is_file()
    }

    pub fn put_action(&self, key: &Digest, a: &Action) -> Result<(), StoreError> {
        let json = serde_json::to_vec_pretty(a).expect("actions serialise");
        self.write_atomic(&self.action_path(key), &json)
    }

    /// The action for `key` if its entry is readable and names valid
    /// digests; an unreadable entry (e.g. truncated by a crash or by hand)
    /// is deleted and reported as absent. Marks the entry as used.
    pub fn get_action(&self, key: &Digest) -> Option<Action> {
        let p = self.action_path(key);
        let bytes = std::fs::read(&p).ok()?;
        match serde_json::from_slice::<Action>(&bytes) {
            Ok(a) if a.digests().is_some() => {
                if let Ok(f) = std::fs::File::options().append(true).open(&p) {
                    let _ = f.set_modified(SystemTime::now());
                }
                Some(a)
            }
            _ => {
                let _ = std::fs::remove_file(&p);
                None
            }
        }
    }

    /// The action for `key` if its entry is readable and names valid
    /// digests, changing nothing (no clean-up, no use mark): for tools
    /// that plan before they act, like `gc --keep`.
    pub fn peek_action(&self, key: &Digest) -> Option<Action> {
        let bytes = std::fs::read(self.action_path(key)).ok()?;
        serde_json::from_slice::<Action>(&bytes)
            .ok()
            .filter(|a| a.digests().is_some())
    }

    /// Where the record of the files written for `stamp` lives
    /// ([`Store::put_written`]).
    fn written_path(&self, stamp: &Digest) -> PathBuf {
        let h = stamp.hex();
        self.root
            .join("written")
            .join(&h[..2])
            .join(format!("{}.json", &h[2..]))
    }

    /// Records the user's files a stage wrote for `stamp` (its key, its
    /// outputs and the paths asked): each file's path, size and digest,
    /// read back from the disk. Files that cannot be read are not
    /// recorded, so they are written again next time.
    pub fn put_written(&self, stamp: &Digest, files: &[PathBuf]) -> Result<(), StoreError> {
        let mut rec = Vec::with_capacity(files.len());
        for f in files {
            let Ok(bytes) = std::fs::read(f) else {
                return Ok(());
            };
            rec.push(Written {
                path: f.clone(),
                size: bytes.len() as u64,
                blake3: Digest::of(&bytes).hex(),
            });
        }
        let json = serde_json::to_vec(&rec).expect("records serialise");
        self.write_atomic(&self.written_path(stamp), &json)
    }

    /// The files recorded for `stamp` if every one of them is still on the
    /// disk with the recorded bytes (size, then digest): writing them again
    /// would change nothing. `None` when there is no record or a file
    /// differs, is missing or unreadable.
    pub fn written_up_to_date(&self, stamp: &Digest) -> Option<Vec<PathBuf>> {
        let bytes = std::fs::read(self.written_path(stamp)).ok()?;
        let rec: Vec<Written> = serde_json::from_slice(&bytes).ok()?;
        for w in &rec {
            let meta = std::fs::metadata(&w.path).ok()?;
            if !meta.is_file() || meta.len() != w.size {
                return None;
            }
            let now = std::fs::read(&w.path).ok()?;
            if Digest::of(&now).hex() != w.blake3 {
                return None;
            }
        }
        Some(rec.into_iter().map(|w| w.path).collect())
    }

    /// Removes an action entry; `Ok(false)` if there was none.
    pub fn remove_action(&self, key: &Digest) -> Result<bool, StoreError> {
        remove(&self.action_path(key))
    }

    /// Every action entry: key, entry (None if unreadable), last use.
    pub fn actions(&self) -> Vec<(Digest, Option<Action>, SystemTime)> {
        let mut out = Vec::new();
        for (name, p, t) in walk2(&self.root.join("actions")) {
            let Some(stem) = name.strip_suffix(".json") else {
                continue;
            };
            let Some(key) = Digest::from_hex(stem) else {
                continue;
            };
            let a = std::fs::read(&p)
                .ok()
                .and_then(|b| serde_json::from_slice::<Action>(&b).ok());
            out.push((key, a, t));
        }
        out.sort_by_key(|x| x.0);
        out
    }

    /// Every blob: digest, size.
    pub fn blobs(&self) -> Vec<(Digest, u64)> {
        let mut out = Vec::new();
        for (name, p, _) in walk2(&self.root.join("blobs")) {
            if let Some(d) = Digest::from_hex(&name) {
                let len = std::fs::metadata(&p).map(|m| m.len()).unwrap_or(0);
                out.push((d, len));
            }
        }
        out.sort();
        out
    }

    pub fn stats(&self) -> Stats {
        let blobs = self.blobs();
        Stats {
            blobs: blobs.len() as u64,
            blob_bytes: blobs.iter().map(|b| b.1).sum(),
            actions: self.actions().len() as u64,
            temp_files: std::fs::read_dir(self.root.join("tmp"))
                .map(|r| r.count() as u64)
                .unwrap_or(0),
        }
    }

    /// Re-hashes every blob and checks every action; removes what is
    /// corrupt, unreadable or incomplete.
    pub fn verify(&self) -> VerifyReport {
        self.verify_with(|_, _, _| Ok(()))
    }

    /// [`Store::verify`], also checking each action's outputs with
    /// `check(action, output name, head)`, `head` being the blob's first
    /// [`CHECK_HEAD`] bytes (enough for a header: every blob was already
    /// read whole and re-hashed once), e.g. that they are the artifact
    /// type the node declares; an entry that fails it is removed (its
    /// blobs stay: they are intact, and other entries may use them).
    pub fn verify_with(
        &self,
        check: impl Fn(&Action, &str, &[u8]) -> Result<(), String>,
    ) -> VerifyReport {
        let mut r = VerifyReport::default();
        for (d, _) in self.blobs() {
            let p = self.blob_path(&d);
            match std::fs::read(&p) {
                Ok(b) if Digest::of(&b) == d => r.blobs_ok += 1,
                Ok(_) => {
                    r.blobs_corrupt.push(d.hex());
                    match remove(&p) {
                        Ok(removed) => r.blobs_removed += removed as u64,
                        Err(e) => r.errors.push(e.to_string()),
                    }
                }
                Err(e) => r.errors.push(io_err(&p)(e).to_string()),
            }
        }
        for (k, a, _) in self.actions() {
            // Which list a damaged entry goes in, and what to record.
            let damage: Option<(&mut Vec<String>, String)> = match a.as_ref() {
                Some(a) => match a.digests() {
                    None => Some((&mut r.actions_unreadable, k.hex())),
                    Some(ds) if !ds.values().all(|d| self.has_blob(d)) => {
                        Some((&mut r.actions_incomplete, k.hex()))
                    }
                    Some(ds) => ds
                        .iter()
                        .find_map(|(name, d)| {
                            check(a, name, &head(&self.blob_path(d), CHECK_HEAD))
                                .err()
                                .map(|why| format!("{}: {name}: {why}", k.hex()))
                        })
                        .map(|w| (&mut r.actions_wrong_type, w)),
                },
                None => Some((&mut r.actions_unreadable, k.hex())),
            };
            match damage {
                None => r.actions_ok += 1,
                Some((list, what)) => {
                    list.push(what);
                    match self.remove_action(&k) {
                        Ok(removed) => r.actions_removed += removed as u64,
                        Err(e) => r.errors.push(e.to_string()),
                    }
                }
            }
        }
        r
    }

    /// Removes action entries the policy does not keep, then every blob no
    /// remaining entry references, and stale temporary files. Counts only
    /// what was removed; an entry or blob that could not be removed is
    /// reported in `errors` and still counts as present (its blobs stay).
    pub fn gc(&self, policy: &GcPolicy) -> GcReport {
        let mut r = GcReport::default();
        let now = SystemTime::now();
        let blob_sizes: BTreeMap<Digest, u64> = self.blobs().into_iter().collect();
        let mut live: Vec<(Digest, Action, SystemTime)> = Vec::new();
        // Entries that stay whatever happens (a failed removal).
        let mut stuck: Vec<Action> = Vec::new();
        let mut drop = |k: &Digest, a: Option<Action>, r: &mut GcReport| match self.remove_action(k)
        {
            Ok(removed) => r.actions_removed += removed as u64,
            Err(e) => {
                r.errors.push(e.to_string());
                stuck.extend(a);
            }
        };
        for (k, a, t) in self.actions() {
            let Some(a) = a else {
                drop(&k, None, &mut r);
                continue;
            };
            let unresolved = policy
                .keep_stages
                .contains(&(a.pipeline.clone(), a.stage.clone()));
            let kept_by_set = policy.keep.as_ref().is_none_or(|s| s.contains(&k));
            let keep = (kept_by_set || unresolved)
                && policy
                    .older_than
                    .is_none_or(|age| now.duration_since(t).unwrap_or_default() <= age);
            if keep {
                if !kept_by_set {
                    r.actions_kept_unresolved += 1;
                }
                live.push((k, a, t));
            } else {
                drop(&k, Some(a), &mut r);
            }
        }
        if let Some(max) = policy.max_bytes {
            // Most recently used first; keep while the referenced bytes fit.
            live.sort_by(|a, b| b.2.cmp(&a.2).then(a.0.cmp(&b.0)));
            let mut counted: BTreeSet<Digest> = BTreeSet::new();
            let mut total = 0u64;
            let mut kept = Vec::new();
            for (k, a, t) in live {
                let ds = a.digests().unwrap_or_default();
                let extra: u64 = ds
                    .values()
                    .filter(|d| !counted.contains(d))
                    .map(|d| blob_sizes.get(d).copied().unwrap_or(0))
                    .sum();
                if total + extra <= max {
                    total += extra;
                    counted.extend(ds.values().copied());
                    kept.push((k, a, t));
                } else {
                    drop(&k, Some(a), &mut r);
                }
            }
            live = kept;
        }
        let referenced: BTreeSet<Digest> = live
            .iter()
            .map(|(_, a, _)| a)
            .chain(stuck.iter())
            .flat_map(|a| a.digests().unwrap_or_default().into_values())
            .collect();
        for (d, size) in blob_sizes {
            if referenced.contains(&d) {
                continue;
            }
            match remove(&self.blob_path(&d)) {
                Ok(true) => {
                    r.blobs_removed += 1;
                    r.bytes_freed += size;
                }
                Ok(false) => {}
                Err(e) => r.errors.push(e.to_string()),
            }
        }
        // Temporary files older than an hour belong to dead processes.
        if let Ok(rd) = std::fs::read_dir(self.root.join("tmp")) {
            for e in rd.flatten() {
                let old = e
                    .metadata()
                    .and_then(|m| m.modified())
                    .map(|t| now.duration_since(t).unwrap_or_default() > Duration::from_secs(3600))
                    .unwrap_or(false);
                if old {
                    match remove(&e.path()) {
                        Ok(removed) => r.temp_removed += removed as u64,
                        Err(e) => r.errors.push(e.to_string()),
                    }
                }
            }
        }
        r
    }
}

impl crate::tier::Cas for Store {
    fn put_blob(&self, bytes: &[u8]) -> Result<Digest, StoreError> {
        Store::put_blob(self, bytes)
    }
    fn get_blob(&self, d: &Digest) -> Result<Option<Vec<u8>>, StoreError> {
        Store::get_blob(self, d)
    }
    fn find_missing(&self, ds: &[Digest]) -> Result<Vec<Digest>, StoreError> {
        Ok(ds.iter().filter(|d| !self.has_blob(d)).copied().collect())
    }
    fn name(&self) -> String {
        self.root.display().to_string()
    }
    /// A store folder as another process's shared tier (a folder on a
    /// shared filesystem): blobs are addressed by BLAKE3 there too.
    fn cas_ref(&self, d: &Digest) -> Option<crate::tier::CasRef> {
        let m = std::fs::metadata(self.blob_path(d)).ok()?;
        Some(crate::tier::CasRef {
            hash: d.hex(),
            size: m.len(),
        })
    }
}

impl crate::tier::ActionCache for Store {
    fn get_action(&self, key: &Digest) -> Result<Option<Action>, StoreError> {
        Ok(Store::get_action(self, key))
    }
    fn put_action(&self, key: &Digest, a: &Action) -> Result<(), StoreError> {
        Store::put_action(self, key, a)
    }
}

/// Files two levels down (`dir/xx/name`): (name, path, modified).
fn walk2(dir: &Path) -> Vec<(String, PathBuf, SystemTime)> {
    let mut out = Vec::new();
    let Ok(rd) = std::fs::read_dir(dir) else {
        return out;
    };
    for sub in rd.flatten() {
        let prefix = sub.file_name().to_string_lossy().into_owned();
        let Ok(rd2) = std::fs::read_dir(sub.path()) else {
            continue;
        };
        for e in rd2.flatten() {
            let name = format!("{prefix}{}", e.file_name().to_string_lossy());
            let t = e
                .metadata()
                .and_then(|m| m.modified())
                .unwrap_or(SystemTime::UNIX_EPOCH);
            out.push((name, e.path(), t));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn action(outputs: &[(&str, Digest)]) -> Action {
        Action {
            kind: "k".into(),
            stage: "s".into(),
            pipeline: "p".into(),
            outputs: outputs
                .iter()
                .map(|(n, d)| (n.to_string(), d.hex()))
                .collect(),
            seconds: 0.0,
            worker: String::new(),
        }
    }

    #[test]
    fn blobs_round_trip_and_corruption_is_a_miss() {
        let dir = tempfile::tempdir().unwrap();
        let s = Store::open(dir.path()).unwrap();
        let d = s.put_blob(b"hello").unwrap();
        assert_eq!(d, Digest::of(b"hello"));
        assert_eq!(s.get_blob(&d).unwrap().unwrap(), b"hello");
        let p = s.blob_path(&d);
        let mut bytes = std::fs::read(&p).unwrap();
        bytes[0] ^= 1;
        std::fs::write(&p, bytes).unwrap();
        assert!(s.get_blob(&d).unwrap().is_none());
        assert!(!p.exists(), "a corrupt blob is removed");
        assert_eq!(Digest::from_hex(&d.hex()), Some(d));
    }

    #[test]
    fn truncated_action_is_a_miss_and_verify_cleans_up() {
        let dir = tempfile::tempdir().unwrap();
        let s = Store::open(dir.path()).unwrap();
        let b = s.put_blob(b"x").unwrap();
        let k1 = Digest::of(b"k1");
        let k2 = Digest::of(b"k2");
        s.put_action(&k1, &action(&[("out", b)])).unwrap();
        s.put_action(&k2, &action(&[("out", Digest::of(b"absent"))]))
            .unwrap();
        assert_eq!(s.get_action(&k1).unwrap().outputs["out"], b.hex());
        let p = s.action_path(&k1);
        let full = std::fs::read(&p).unwrap();
        std::fs::write(&p, &full[..full.len() / 2]).unwrap();
        assert!(s.get_action(&k1).is_none());
        let r = s.verify();
        assert_eq!(r.blobs_ok, 1);
        assert_eq!(r.actions_incomplete, vec![k2.hex()]);
        assert!(s.actions().is_empty());
    }

    #[test]
    fn gc_keeps_what_is_referenced() {
        let dir = tempfile::tempdir().unwrap();
        let s = Store::open(dir.path()).unwrap();
        let a = s.put_blob(b"a").unwrap();
        let b = s.put_blob(b"bb").unwrap();
        let ka = Digest::of(b"ka");
        let kb = Digest::of(b"kb");
        s.put_action(&ka, &action(&[("o", a)])).unwrap();
        s.put_action(&kb, &action(&[("o", b)])).unwrap();
        let r = s.gc(&GcPolicy {
            keep: Some([ka].into_iter().collect()),
            ..Default::default()
        });
        assert_eq!(
            (r.actions_removed, r.blobs_removed, r.bytes_freed),
            (1, 1, 2)
        );
        assert!(s.get_blob(&a).unwrap().is_some());
        assert!(s.get_blob(&b).unwrap().is_none());
        let r = s.gc(&GcPolicy {
            max_bytes: Some(0),
            ..Default::default()
        });
        assert_eq!(r.actions_removed, 1);
        assert_eq!(s.stats().blobs, 0);
    }
}
