//! `multipart/byteranges` (RFC 9110 §14.6) and the streaming response body that reads a file
//! with positioned reads, one bounded chunk at a time.

use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};

use bytes::Bytes;
use http_body::{Frame, SizeHint};

use super::range::ByteRange;
use crate::store::assets::ReadAt;

/// Length of the multipart boundary string.
pub const BOUNDARY_LEN: usize = 32;

/// Bytes read from the file per body frame.
pub const CHUNK: u64 = 64 * 1024;

/// Responses up to this many bytes are built in one buffer; larger ones stream.
pub const INLINE_MAX: u64 = 256 * 1024;

/// A fresh boundary: `BOUNDARY_LEN` characters from the operating system's random source (the
/// content of a part can then not be made to contain it by anyone who does not know it).
pub fn new_boundary() -> String {
    let mut raw = [0u8; BOUNDARY_LEN / 2];
    if getrandom::fill(&mut raw).is_err() {
        // Still unpredictable enough to never collide by accident.
        let t = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        raw.copy_from_slice(&t.to_le_bytes()[..BOUNDARY_LEN / 2]);
    }
    crate::store::assets::hex(&raw)
}

/// The bytes written before part `index`'s data.
pub fn part_header(boundary: &str, content_type: &str, index: usize, r: ByteRange, total: u64) -> String {
    let lead = if index == 0 { "" } else { "\r\n" };
    format!(
        "{lead}--{boundary}\r\nContent-Type: {content_type}\r\nContent-Range: bytes {}-{}/{total}\r\n\r\n",
        r.start,
        r.end - 1
    )
}

/// The closing delimiter.
pub fn closing(boundary: &str) -> String {
    format!("\r\n--{boundary}--\r\n")
}

/// Exact length of a multipart body for these ranges.
pub fn multipart_len(boundary: &str, content_type: &str, ranges: &[ByteRange], total: u64) -> u64 {
    let fixed = ranges
        .iter()
        .enumerate()
        .map(|(i, r)| part_header(boundary, content_type, i, *r, total).len() as u64 + r.len())
        .sum::<u64>();
    fixed + closing(boundary).len() as u64
}

/// Multipart framing of a [`RangeBody`].
#[derive(Debug, Clone)]
pub struct Framing {
    /// Boundary string.
    pub boundary: Arc<str>,
    /// Content type of every part.
    pub content_type: &'static str,
    /// The file's full length, for `Content-Range`.
    pub total: u64,
}

/// Reads `r` from `file` into `out`.
pub fn read_range(file: &dyn ReadAt, r: ByteRange, out: &mut Vec<u8>) -> std::io::Result<()> {
    let start = out.len();
    out.resize(start + r.len() as usize, 0);
    file.read_exact_at(&mut out[start..], r.start)
}

/// Builds a whole (small) response in memory: the ranges' bytes, framed when `framing` is set.
/// `len` is the expected length (the buffer is allocated once at that size).
pub fn build_inline(
    file: &dyn ReadAt,
    ranges: &[ByteRange],
    framing: Option<&Framing>,
    len: usize,
) -> std::io::Result<Vec<u8>> {
    let mut out = Vec::with_capacity(len);
    for (i, r) in ranges.iter().enumerate() {
        if let Some(f) = framing {
            out.extend_from_slice(part_header(&f.boundary, f.content_type, i, *r, f.total).as_bytes());
        }
        read_range(file, *r, &mut out)?;
    }
    if let Some(f) = framing {
        out.extend_from_slice(closing(&f.boundary).as_bytes());
    }
    Ok(out)
}

/// A response body over ranges of a file, produced lazily: at most [`CHUNK`] bytes of file data
/// (or one part header) are in memory at a time, and the next chunk is read only when the
/// connection asks for it, so a slow reader holds the server to one chunk.
///
/// Reads are positioned reads (`pread`) done inline: assets are local, immutable and usually in
/// the page cache, where a 64 KiB read takes microseconds.
#[derive(Debug)]
pub struct RangeBody {
    file: Arc<dyn ReadAt>,
    ranges: Vec<ByteRange>,
    framing: Option<Framing>,
    next: usize,
    pos: u64,
    end: u64,
    remaining: u64,
    closed: bool,
}

impl RangeBody {
    /// A body of `ranges` of `file`, as multipart when `framing` is given.
    pub fn new(file: Arc<dyn ReadAt>, ranges: Vec<ByteRange>, framing: Option<Framing>) -> Self {
        let remaining = match &framing {
            Some(f) => multipart_len(&f.boundary, f.content_type, &ranges, f.total),
            None => ranges.iter().map(|r| r.len()).sum(),
        };
        Self {
            file,
            ranges,
            framing,
            next: 0,
            pos: 0,
            end: 0,
            remaining,
            closed: false,
        }
    }

    /// Bytes this body will produce in all.
    pub fn len(&self) -> u64 {
        self.remaining
    }

    /// True when nothing is left to send.
    pub fn is_empty(&self) -> bool {
        self.remaining == 0
    }

    fn emit(&mut self, b: Vec<u8>) -> Poll<Option<Result<Frame<Bytes>, std::io::Error>>> {
        self.remaining = self.remaining.saturating_sub(b.len() as u64);
        Poll::Ready(Some(Ok(Frame::data(Bytes::from(b)))))
    }
}

impl http_body::Body for RangeBody {
    type Data = Bytes;
    type Error = std::io::Error;

    fn poll_frame(self: Pin<&mut Self>, _cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Self::Data>, Self::Error>>> {
        let this = self.get_mut();
        loop {
            if this.pos < this.end {
                let r = ByteRange {
                    start: this.pos,
                    end: this.end.min(this.pos + CHUNK),
                };
                let mut buf = Vec::new();
                if let Err(e) = read_range(this.file.as_ref(), r, &mut buf) {
                    return Poll::Ready(Some(Err(e)));
                }
                this.pos = r.end;
                return this.emit(buf);
            }
            let Some(&r) = this.ranges.get(this.next) else {
                break;
            };
            let index = this.next;
            this.next += 1;
            this.pos = r.start;
            this.end = r.end;
            if let Some(f) = &this.framing {
                let h = part_header(&f.boundary, f.content_type, index, r, f.total).into_bytes();
                return this.emit(h);
            }
            // Plain body: go straight to the data.
        }
        if !this.closed {
            this.closed = true;
            if let Some(f) = &this.framing {
                let c = closing(&f.boundary).into_bytes();
                return this.emit(c);
            }
        }
        Poll::Ready(None)
    }

    fn is_end_stream(&self) -> bool {
        self.remaining == 0 && (self.closed || self.framing.is_none()) && self.pos >= self.end
    }

    fn size_hint(&self) -> SizeHint {
        SizeHint::with_exact(self.remaining)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::http::range::COALESCE_GAP;

    /// The coalesce gap covers the longest part header this server can write (20-digit numbers,
    /// the longest content type), so merged gaps pay for every extra part.
    #[test]
    fn coalesce_gap_covers_the_longest_part_header() {
        let b = new_boundary();
        assert_eq!(b.len(), BOUNDARY_LEN);
        let r = ByteRange {
            start: u64::MAX - 2,
            end: u64::MAX - 1,
        };
        let h = part_header(&b, "application/octet-stream", 1, r, u64::MAX);
        assert!((h.len() as u64) <= COALESCE_GAP, "{} > {COALESCE_GAP}", h.len());
    }

    use std::fs::File;

    fn temp_file(bytes: &[u8]) -> (std::path::PathBuf, Arc<dyn ReadAt>) {
        let p = std::env::temp_dir().join(format!("canopy-mp-{}-{}", std::process::id(), new_boundary()));
        std::fs::write(&p, bytes).expect("write");
        let f = File::open(&p).expect("open");
        (p, Arc::new(f))
    }

    fn drain(mut body: RangeBody) -> Vec<u8> {
        use http_body::Body;
        let waker = std::task::Waker::noop();
        let mut cx = Context::from_waker(waker);
        let mut out = Vec::new();
        let hint = body.size_hint().exact();
        while let Poll::Ready(Some(frame)) = Pin::new(&mut body).poll_frame(&mut cx) {
            let data = frame.expect("frame").into_data().expect("data");
            assert!(data.len() as u64 <= CHUNK.max(300));
            out.extend_from_slice(&data);
        }
        assert_eq!(Some(out.len() as u64), hint);
        out
    }

    #[test]
    fn streaming_and_inline_bodies_agree() {
        let data: Vec<u8> = (0..300_000u32).map(|i| (i * 7 % 251) as u8).collect();
        let (p, f) = temp_file(&data);
        let ranges = vec![
            ByteRange { start: 0, end: 10 },
            ByteRange {
                start: 1000,
                end: 140_000,
            },
            ByteRange {
                start: 299_990,
                end: 300_000,
            },
        ];
        let framing = Framing {
            boundary: Arc::from(new_boundary()),
            content_type: "application/octet-stream",
            total: 300_000,
        };
        let inline = build_inline(f.as_ref(), &ranges, Some(&framing), 0).expect("inline");
        let streamed = drain(RangeBody::new(f.clone(), ranges.clone(), Some(framing.clone())));
        assert_eq!(inline, streamed);
        assert_eq!(
            inline.len() as u64,
            multipart_len(&framing.boundary, framing.content_type, &ranges, 300_000)
        );
        let plain = drain(RangeBody::new(
            f.clone(),
            vec![ByteRange { start: 5, end: 200_005 }],
            None,
        ));
        assert_eq!(plain, &data[5..200_005]);
        let _ = std::fs::remove_file(p);
    }
}
