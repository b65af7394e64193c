//! The store as tiers: a small [`Cas`] + [`ActionCache`] pair of traits,
//! implemented by the local disk store ([`crate::Store`]) and by remote
//! tiers (the Remote Execution API client lives in `matflow-rpc`; the
//! engine knows it only through these traits), and [`Tiered`], a local
//! disk tier in front of an optional remote one (read-through,
//! write-through).
//!
//! matflow addresses everything by BLAKE3. A remote tier may address
//! blobs by another digest function (most REAPI servers offer SHA-256
//! only); it then keeps the BLAKE3 → its own digest mapping ([`CasRef`])
//! and re-hashes every blob it returns with BLAKE3, so a blob that does not
//! match is a miss, never a wrong result.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use crate::node::Bytes;
use crate::store::{Action, Digest, Store, StoreError};

/// A blob's address in a tier's own digest function (hex hash, size).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CasRef {
    pub hash: String,
    pub size: u64,
}

/// Content-addressed blobs, by BLAKE3 digest.
pub trait Cas: Send + Sync {
    /// Stores bytes; returns their BLAKE3 digest.
    fn put_blob(&self, bytes: &[u8]) -> Result<Digest, StoreError>;
    /// The bytes, if present and hashing to `d`; anything else is `None`.
    fn get_blob(&self, d: &Digest) -> Result<Option<Vec<u8>>, StoreError>;
    /// The digests of `ds` this tier does not hold.
    fn find_missing(&self, ds: &[Digest]) -> Result<Vec<Digest>, StoreError>;
    /// A name for messages and reports (a folder, an endpoint).
    fn name(&self) -> String;
    /// The blob's address in this tier's digest function, when known.
    fn cas_ref(&self, _d: &Digest) -> Option<CasRef> {
        None
    }
    /// Tells the tier where a blob lives in its digest function (learnt
    /// from a peer that uploaded it).
    fn learn(&self, _d: &Digest, _r: &CasRef) {}
}

/// Node key → the action that computed it.
pub trait ActionCache: Send + Sync {
    fn get_action(&self, key: &Digest) -> Result<Option<Action>, StoreError>;
    fn put_action(&self, key: &Digest, a: &Action) -> Result<(), StoreError>;
}

/// A tier that is both (what a remote cache server offers).
pub trait StoreTier: Cas + ActionCache {}
impl<T: Cas + ActionCache> StoreTier for T {}

/// Bytes kept in memory for the life of a process, so a stage's inputs
/// are not read and hashed twice; cleared when it outgrows its cap.
struct Memo {
    blobs: HashMap<Digest, Bytes>,
    bytes: u64,
}

/// A local disk tier, optionally in front of a remote tier.
pub struct Tiered {
    local: Store,
    remote: Option<Arc<dyn StoreTier>>,
    memo: Mutex<Memo>,
    memo_cap: u64,
    up: AtomicU64,
    down: AtomicU64,
}

impl Tiered {
    pub fn new(local: Store, remote: Option<Arc<dyn StoreTier>>) -> Tiered {
        Tiered {
            local,
            remote,
            memo: Mutex::new(Memo {
                blobs: HashMap::new(),
                bytes: 0,
            }),
            memo_cap: 4 << 30,
            up: AtomicU64::new(0),
            down: AtomicU64::new(0),
        }
    }

    pub fn local(&self) -> &Store {
        &self.local
    }

    pub fn remote(&self) -> Option<&dyn StoreTier> {
        self.remote.as_deref()
    }

    /// "DIR" or "DIR + grpc://host:port".
    pub fn describe(&self) -> String {
        match &self.remote {
            Some(r) => format!("{} + {}", self.local.root().display(), r.name()),
            None => self.local.root().display().to_string(),
        }
    }

    /// Bytes uploaded to and downloaded from the remote tier so far.
    pub fn moved(&self) -> (u64, u64) {
        (
            self.up.load(Ordering::Relaxed),
            self.down.load(Ordering::Relaxed),
        )
    }

    fn remember(&self, d: Digest, b: &Bytes) {
        let mut m = self.memo.lock().unwrap();
        if m.blobs.contains_key(&d) {
            return;
        }
        let n = b.len() as u64;
        if m.bytes + n > self.memo_cap {
            m.blobs.clear();
            m.bytes = 0;
        }
        if n <= self.memo_cap {
            m.blobs.insert(d, b.clone());
            m.bytes += n;
        }
    }

    fn forget(&self, d: &Digest) {
        let mut m = self.memo.lock().unwrap();
        if let Some(b) = m.blobs.remove(d) {
            m.bytes -= b.len() as u64;
        }
    }

    /// Whether a remote tier is configured (lookups may cross the
    /// network).
    pub fn has_remote(&self) -> bool {
        self.remote.is_some()
    }

    /// A cache hit for `key`: its outputs, when the entry exists and every
    /// blob is there. Local blobs are re-hashed now (a corrupt one makes
    /// this a miss); blobs only the remote tier holds are checked for
    /// presence and re-hashed when read.
    pub fn lookup(&self, key: &Digest) -> Result<Option<BTreeMap<String, Digest>>, StoreError> {
        // An entry without outputs (or with malformed ones) was not written
        // by a finished stage: a miss, never an empty result.
        let usable = |a: &Action| a.digests().filter(|ds| !ds.is_empty());
        if let Some(a) = self.local.get_action(key) {
            let ds = usable(&a).unwrap_or_default();
            let mut intact = !ds.is_empty();
            for d in ds.values() {
                if self.memo.lock().unwrap().blobs.contains_key(d) {
                    continue;
                }
                match self.local.get_blob(d)? {
                    Some(b) => self.remember(*d, &Arc::new(b)),
                    None => {
                        intact = false;
                        break;
                    }
                }
            }
            if intact {
                return Ok(Some(ds));
            }
            if self.remote.is_none() {
                // A miss either way; an entry that cannot be removed (a
                // read-only cache) is overwritten when the stage re-runs,
                // or reported by `cache verify`.
                let _ = self.local.remove_action(key);
                return Ok(None);
            }
        }
        let Some(r) = &self.remote else {
            return Ok(None);
        };
        let Some(a) = r.get_action(key)? else {
            return Ok(None);
        };
        let Some(ds) = usable(&a) else {
            return Ok(None);
        };
        let all: Vec<Digest> = ds.values().copied().collect();
        let not_local = self.local.find_missing(&all)?;
        if !r.find_missing(&not_local)?.is_empty() {
            return Ok(None);
        }
        // The entry now lives here too; its blobs come when read.
        self.local.put_action(key, &a)?;
        Ok(Some(ds))
    }

    /// The blob's bytes, verified, from memory, the local tier or the
    /// remote one (then kept locally).
    pub fn get(&self, d: &Digest) -> Result<Option<Bytes>, StoreError> {
        if let Some(b) = self.memo.lock().unwrap().blobs.get(d) {
            return Ok(Some(b.clone()));
        }
        if let Some(b) = self.local.get_blob(d)? {
            let b = Arc::new(b);
            self.remember(*d, &b);
            return Ok(Some(b));
        }
        let Some(r) = &self.remote else {
            return Ok(None);
        };
        match r.get_blob(d)? {
            Some(b) => {
                self.down.fetch_add(b.len() as u64, Ordering::Relaxed);
                self.local.put_blob(&b)?;
                let b = Arc::new(b);
                self.remember(*d, &b);
                Ok(Some(b))
            }
            None => Ok(None),
        }
    }

    /// A blob read turned out corrupt or missing downstream: drop it from
    /// memory so the next read goes to the tiers again.
    pub fn invalidate(&self, d: &Digest) {
        self.forget(d);
    }

    /// Stores bytes in every tier (the remote one only when it lacks them).
    pub fn put(&self, bytes: &Bytes) -> Result<Digest, StoreError> {
        let d = self.local.put_blob(bytes)?;
        self.remember(d, bytes);
        if let Some(r) = &self.remote {
            if !r.find_missing(&[d])?.is_empty() {
                r.put_blob(bytes)?;
                self.up.fetch_add(bytes.len() as u64, Ordering::Relaxed);
            }
        }
        Ok(d)
    }

    pub fn put_action(&self, key: &Digest, a: &Action) -> Result<(), StoreError> {
        self.local.put_action(key, a)?;
        if let Some(r) = &self.remote {
            r.put_action(key, a)?;
        }
        Ok(())
    }

    /// Forgets a local entry (a remote one can only be overwritten).
    pub fn remove_action(&self, key: &Digest) {
        // Best effort: the stage re-runs uncached and overwrites it.
        let _ = self.local.remove_action(key);
    }

    /// Where the remote tier keeps a blob, for telling a peer.
    pub fn cas_ref(&self, d: &Digest) -> Option<CasRef> {
        self.remote.as_ref().and_then(|r| r.cas_ref(d))
    }

    /// Makes sure the remote tier holds a blob this process has (uploading
    /// it from the local tier if need be); returns where it lives there.
    /// `Ok(None)` when there is no remote tier or nobody has the bytes.
    pub fn ensure_remote(&self, d: &Digest) -> Result<Option<CasRef>, StoreError> {
        let Some(r) = &self.remote else {
            return Ok(None);
        };
        if let Some(cr) = r.cas_ref(d) {
            if r.find_missing(&[*d])?.is_empty() {
                return Ok(Some(cr));
            }
        }
        let b = match self.memo.lock().unwrap().blobs.get(d) {
            Some(b) => Some(b.clone()),
            None => self.local.get_blob(d)?.map(Arc::new),
        };
        let Some(b) = b else { return Ok(None) };
        r.put_blob(&b)?;
        self.up.fetch_add(b.len() as u64, Ordering::Relaxed);
        Ok(r.cas_ref(d))
    }

    pub fn learn(&self, d: &Digest, r: &CasRef) {
        if let Some(t) = &self.remote {
            t.learn(d, r);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A second local store standing in for a remote tier.
    struct Other(Store);
    impl Cas for Other {
        fn put_blob(&self, b: &[u8]) -> Result<Digest, StoreError> {
            self.0.put_blob(b)
        }
        fn get_blob(&self, d: &Digest) -> Result<Option<Vec<u8>>, StoreError> {
            self.0.get_blob(d)
        }
        fn find_missing(&self, ds: &[Digest]) -> Result<Vec<Digest>, StoreError> {
            Cas::find_missing(&self.0, ds)
        }
        fn name(&self) -> String {
            "other".into()
        }
    }
    impl ActionCache for Other {
        fn get_action(&self, k: &Digest) -> Result<Option<Action>, StoreError> {
            Ok(self.0.get_action(k))
        }
        fn put_action(&self, k: &Digest, a: &Action) -> Result<(), StoreError> {
            self.0.put_action(k, a)
        }
    }

    fn action(d: Digest) -> Action {
        Action {
            kind: "k".into(),
            stage: "s".into(),
            pipeline: "p".into(),
            outputs: [("o".to_string(), d.hex())].into_iter().collect(),
            seconds: 0.0,
            worker: String::new(),
        }
    }

    #[test]
    fn two_local_tiers_share_one_remote_read_through() {
        let dir = tempfile::tempdir().unwrap();
        let remote: Arc<dyn StoreTier> =
            Arc::new(Other(Store::open(dir.path().join("r")).unwrap()));
        let a = Tiered::new(
            Store::open(dir.path().join("a")).unwrap(),
            Some(remote.clone()),
        );
        let b = Tiered::new(
            Store::open(dir.path().join("b")).unwrap(),
            Some(remote.clone()),
        );
        let bytes: Bytes = Arc::new(b"payload".to_vec());
        let d = a.put(&bytes).unwrap();
        let key = Digest::of(b"key");
        a.put_action(&key, &action(d)).unwrap();
        assert_eq!(a.moved().0, 7);
        // b has nothing locally: the hit comes from the remote tier, the
        // bytes on first read, then from its own disk.
        assert!(b.local().get_action(&key).is_none());
        let hit = b.lookup(&key).unwrap().unwrap();
        assert_eq!(hit["o"], d);
        assert_eq!(b.get(&d).unwrap().unwrap().as_slice(), b"payload");
        assert_eq!(b.moved().1, 7);
        assert!(b.local().has_blob(&d));
        // A key nobody computed is a miss everywhere.
        assert!(b.lookup(&Digest::of(b"other")).unwrap().is_none());
    }

    #[test]
    fn a_corrupt_local_blob_is_a_miss() {
        let dir = tempfile::tempdir().unwrap();
        let t = Tiered::new(Store::open(dir.path()).unwrap(), None);
        let d = t.local().put_blob(b"abc").unwrap();
        let key = Digest::of(b"k");
        t.local().put_action(&key, &action(d)).unwrap();
        std::fs::write(t.local().blob_path(&d), b"abd").unwrap();
        assert!(t.lookup(&key).unwrap().is_none());
        assert!(t.local().get_action(&key).is_none(), "entry removed");
    }

    #[test]
    fn an_entry_without_outputs_is_a_miss_in_either_tier() {
        let dir = tempfile::tempdir().unwrap();
        let remote: Arc<dyn StoreTier> =
            Arc::new(Other(Store::open(dir.path().join("r")).unwrap()));
        let t = Tiered::new(
            Store::open(dir.path().join("a")).unwrap(),
            Some(remote.clone()),
        );
        let key = Digest::of(b"key");
        let mut empty = action(Digest::of(b"x"));
        empty.outputs.clear();
        remote.put_action(&key, &empty).unwrap();
        assert!(
            t.lookup(&key).unwrap().is_none(),
            "remote entry without outputs"
        );
        t.local().put_action(&key, &empty).unwrap();
        assert!(
            t.lookup(&key).unwrap().is_none(),
            "local entry without outputs"
        );
        let mut bad = action(Digest::of(b"x"));
        bad.outputs.insert("o".into(), "not hex".into());
        t.local().put_action(&key, &bad).unwrap();
        assert!(t.lookup(&key).unwrap().is_none(), "malformed digest");
    }
}
