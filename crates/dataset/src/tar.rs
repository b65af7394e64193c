//! Deterministic POSIX ustar archives, the WebDataset shard format: every
//! member a regular file, mode 0644, owner 0:0, time 0 (the epoch), so the
//! same members in the same order give the same bytes on any machine.
//! Python's `tarfile` and the `webdataset` loader read them.

use std::fmt;

/// Bytes per tar block.
pub const BLOCK: usize = 512;

/// A member name longer than ustar's 100 bytes (this writer uses no
/// prefix field: dataset member names are short).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TarError {
    #[error("tar member name `{0}` is longer than 100 bytes")]
    NameTooLong(String),
    #[error("tar member name `{0}` is empty or not plain (no `/`, `..`, NUL)")]
    BadName(String),
    #[error("tar member `{name}` is {size} bytes; ustar allows less than 8 GiB")]
    TooLarge { name: String, size: u64 },
    #[error("not a tar archive: {0}")]
    Corrupt(String),
}

/// One member read back: its name and where its bytes lie in the archive.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Entry {
    pub name: String,
    pub offset: usize,
    pub size: usize,
}

impl fmt::Display for Entry {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} ({} B at {})", self.name, self.size, self.offset)
    }
}

fn octal(field: &mut [u8], v: u64) {
    // n − 1 octal digits and a NUL.
    let digits = field.len() - 1;
    let s = format!("{v:0digits$o}");
    field[..digits].copy_from_slice(s.as_bytes());
    field[digits] = 0;
}

/// The 512-byte ustar header of a regular file.
fn header(name: &str, size: u64) -> Result<[u8; BLOCK], TarError> {
    if name.is_empty() || name.contains('/') || name.contains('\0') || name == "." || name == ".." {
        return Err(TarError::BadName(name.to_string()));
    }
    if name.len() > 100 {
        return Err(TarError::NameTooLong(name.to_string()));
    }
    if size >= 1 << 33 {
        return Err(TarError::TooLarge {
            name: name.to_string(),
            size,
        });
    }
    let mut h = [0u8; BLOCK];
    h[..name.len()].copy_from_slice(name.as_bytes());
    octal(&mut h[100..108], 0o644);
    octal(&mut h[108..116], 0);
    octal(&mut h[116..124], 0);
    octal(&mut h[124..136], size);
    octal(&mut h[136..148], 0);
    h[156] = b'0';
    h[257..263].copy_from_slice(b"ustar\0");
    h[263..265].copy_from_slice(b"00");
    // The checksum: the header's byte sum with the field as spaces.
    h[148..156].copy_from_slice(b"        ");
    let sum: u32 = h.iter().map(|&b| b as u32).sum();
    let s = format!("{sum:06o}");
    h[148..154].copy_from_slice(s.as_bytes());
    h[154] = 0;
    h[155] = b' ';
    Ok(h)
}

/// Builds an archive in memory, member by member.
#[derive(Default)]
pub struct Writer {
    out: Vec<u8>,
}

impl Writer {
    pub fn new() -> Writer {
        Writer::default()
    }
    /// Appends a regular file.
    pub fn add(&mut self, name: &str, data: &[u8]) -> Result<(), TarError> {
        self.out
            .extend_from_slice(&header(name, data.len() as u64)?);
        self.out.extend_from_slice(data);
        let pad = (BLOCK - data.len() % BLOCK) % BLOCK;
        self.out.extend(std::iter::repeat_n(0u8, pad));
        Ok(())
    }
    /// The archive: the members and two zero blocks.
    pub fn finish(mut self) -> Vec<u8> {
        self.out.extend(std::iter::repeat_n(0u8, 2 * BLOCK));
        self.out
    }
}

fn parse_octal(field: &[u8]) -> Option<u64> {
    let s = field
        .iter()
        .take_while(|&&b| b != 0 && b != b' ')
        .map(|&b| b as char)
        .collect::<String>();
    let s = s.trim_start_matches(' ');
    if s.is_empty() {
        return Some(0);
    }
    u64::from_str_radix(s, 8).ok()
}

/// The regular-file members of an archive, in order, each checked: the
/// header checksum, the size within the archive; an archive must end with
/// its zero blocks. Other entry types (folders, links, PAX headers) are
/// errors: dataset shards have none.
pub fn read(bytes: &[u8]) -> Result<Vec<Entry>, TarError> {
    let mut at = 0usize;
    let mut out = Vec::new();
    loop {
        let Some(h) = bytes.get(at..at + BLOCK) else {
            return Err(TarError::Corrupt(format!(
                "cut short at byte {at} (no end-of-archive blocks)"
            )));
        };
        if h.iter().all(|&b| b == 0) {
            return Ok(out);
        }
        let stored = parse_octal(&h[148..156])
            .ok_or_else(|| TarError::Corrupt(format!("header at byte {at}: bad checksum field")))?;
        let sum: u64 = h
            .iter()
            .enumerate()
            .map(|(k, &b)| {
                if (148..156).contains(&k) {
                    32
                } else {
                    b as u64
                }
            })
            .sum();
        if sum != stored {
            return Err(TarError::Corrupt(format!(
                "header at byte {at}: checksum {stored:o} does not match {sum:o}"
            )));
        }
        let name_len = h[..100].iter().position(|&b| b == 0).unwrap_or(100);
        let name = String::from_utf8_lossy(&h[..name_len]).into_owned();
        if !matches!(h[156], b'0' | 0) {
            return Err(TarError::Corrupt(format!(
                "member `{name}` at byte {at} is not a regular file (type {:?})",
                h[156] as char
            )));
        }
        let size = parse_octal(&h[124..136]).ok_or_else(|| {
            TarError::Corrupt(format!("member `{name}` at byte {at}: bad size field"))
        })? as usize;
        let offset = at + BLOCK;
        let padded = size.div_ceil(BLOCK) * BLOCK;
        if offset
            .checked_add(padded)
            .is_none_or(|end| end > bytes.len())
        {
            return Err(TarError::Corrupt(format!(
                "member `{name}` ({size} B at byte {offset}) runs past the end"
            )));
        }
        out.push(Entry { name, offset, size });
        at = offset + padded;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn an_archive_reads_back_its_members() {
        let mut w = Writer::new();
        w.add("s00000001.image.png", b"png bytes").unwrap();
        w.add("s00000001.json", &[7u8; 1024]).unwrap();
        w.add("empty", b"").unwrap();
        let a = w.finish();
        assert_eq!(a.len() % BLOCK, 0);
        let e = read(&a).unwrap();
        let names: Vec<&str> = e.iter().map(|e| e.name.as_str()).collect();
        assert_eq!(names, ["s00000001.image.png", "s00000001.json", "empty"]);
        assert_eq!(&a[e[0].offset..e[0].offset + e[0].size], b"png bytes");
        assert_eq!(e[1].size, 1024);
        assert_eq!(e[2].size, 0);
    }

    #[test]
    fn damage_is_reported_not_misread() {
        let mut w = Writer::new();
        w.add("a.txt", b"hello").unwrap();
        let a = w.finish();
        let mut flipped = a.clone();
        flipped[3] ^= 1;
        assert!(read(&flipped).unwrap_err().to_string().contains("checksum"));
        assert!(read(&a[..600])
            .unwrap_err()
            .to_string()
            .contains("past the end"));
        assert!(read(&a[..1024])
            .unwrap_err()
            .to_string()
            .contains("cut short"));
        assert!(matches!(
            Writer::new().add(&"x".repeat(101), b""),
            Err(TarError::NameTooLong(_))
        ));
        assert!(matches!(
            Writer::new().add("../x", b""),
            Err(TarError::BadName(_))
        ));
    }

    proptest! {
        #[test]
        fn any_members_round_trip(files in proptest::collection::vec(
            ("[a-z0-9._-]{1,40}", proptest::collection::vec(any::<u8>(), 0..1500)), 0..6)) {
            let files: Vec<_> = files.into_iter().filter(|(n, _)| n != "." && n != "..").collect();
            let mut w = Writer::new();
            for (n, d) in &files {
                w.add(n, d).unwrap();
            }
            let a = w.finish();
            let e = read(&a).unwrap();
            prop_assert_eq!(e.len(), files.len());
            for (entry, (n, d)) in e.iter().zip(&files) {
                prop_assert_eq!(&entry.name, n);
                prop_assert_eq!(&a[entry.offset..entry.offset + entry.size], &d[..]);
            }
        }
    }
}
