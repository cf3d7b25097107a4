//! File backend: a server's data folder read directly (`/assets/x` → `ROOT/assets/x`), with
//! positioned reads. Used by tests, by `canopy plan`, and to measure the client without a network.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Component, Path, PathBuf};
use std::sync::atomic::AtomicU64;

use bytes::Bytes;

use super::{ByteRange, InFlight, NetError, NetStats, RangeSource};

/// Reads paths under a root folder.
#[derive(Debug)]
pub struct FileSource {
    root: PathBuf,
    stats: NetStats,
    in_flight: AtomicU64,
}

impl FileSource {
    /// A source over `root` (a server's data folder: it holds `assets/`).
    pub fn new(root: impl Into<PathBuf>) -> Self {
        Self {
            root: root.into(),
            stats: NetStats::default(),
            in_flight: AtomicU64::new(0),
        }
    }

    fn resolve(&self, path: &str) -> Result<PathBuf, NetError> {
        let rel = path.strip_prefix('/').ok_or_else(|| NetError::BadPath(path.into()))?;
        let rel = Path::new(rel);
        if rel.components().any(|c| !matches!(c, Component::Normal(_))) {
            return Err(NetError::BadPath(path.into()));
        }
        Ok(self.root.join(rel))
    }

    fn open(&self, path: &str) -> Result<(File, u64), NetError> {
        let p = self.resolve(path)?;
        let io = |source| NetError::Io {
            path: path.into(),
            source,
        };
        let f = File::open(&p).map_err(io)?;
        let size = f.metadata().map_err(io)?.len();
        Ok((f, size))
    }
}

impl RangeSource for FileSource {
    async fn get(&self, path: &str) -> Result<Bytes, NetError> {
        let _g = InFlight::new(&self.stats, &self.in_flight);
        let p = self.resolve(path)?;
        let data = std::fs::read(&p).map_err(|source| NetError::Io {
            path: path.into(),
            source,
        })?;
        self.stats.add_request(data.len() as u64);
        Ok(Bytes::from(data))
    }

    async fn fetch(&self, path: &str, ranges: &[ByteRange]) -> Result<Vec<Bytes>, NetError> {
        let _g = InFlight::new(&self.stats, &self.in_flight);
        let (f, size) = self.open(path)?;
        let mut out = Vec::with_capacity(ranges.len());
        let mut total = 0u64;
        for r in ranges {
            if r.start >= r.end || r.end > size {
                return Err(NetError::OutOfRange {
                    path: path.into(),
                    start: r.start,
                    end: r.end,
                    size,
                });
            }
            let mut buf = vec![0u8; (r.end - r.start) as usize];
            f.read_exact_at(&mut buf, r.start).map_err(|source| NetError::Io {
                path: path.into(),
                source,
            })?;
            total += buf.len() as u64;
            out.push(Bytes::from(buf));
        }
        self.stats.add_request(total);
        Ok(out)
    }

    fn stats(&self) -> &NetStats {
        &self.stats
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn reads_ranges_and_refuses_escapes() {
        let dir = std::env::temp_dir().join(format!("canopy-filesource-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("assets")).expect("mkdir");
        std::fs::write(dir.join("assets/a.bin"), b"0123456789").expect("write");
        let s = FileSource::new(&dir);
        let got = s.fetch("/assets/a.bin", &[2..4, 8..10]).await.expect("fetch");
        assert_eq!(&got[0][..], b"23");
        assert_eq!(&got[1][..], b"89");
        assert!(matches!(
            s.fetch("/assets/a.bin", std::slice::from_ref(&(8..11))).await,
            Err(NetError::OutOfRange { size: 10, .. })
        ));
        assert!(matches!(s.get("/assets/../x").await, Err(NetError::BadPath(_))));
        assert!(matches!(s.get("assets/a.bin").await, Err(NetError::BadPath(_))));
        assert_eq!(s.stats().snapshot().requests, 1);
        std::fs::remove_dir_all(&dir).ok();
    }
}
