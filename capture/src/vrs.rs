//! A reader for the parts of the VRS container format (facebookresearch/vrs) that aim
//! needs: file header, description record (stream tags and file tags such as Aria's
//! `calib_json`), the index record (classic format, optionally zstd-compressed), record
//! headers, lz4/zstd-compressed payloads, DataLayout metadata blocks and the image
//! content blocks of Aria's RGB stream (214-1).
//!
//! Layout (all little-endian, packed):
//! - file header: magic1 u32, magic2 u32, creation id u64, file header size u32,
//!   record header size u32, index record offset i64, description record offset i64,
//!   first user record offset i64, 3 x u64 reserved, magic3 u32, format version u32.
//! - record header: record size u32 (header + payload), previous record size u32,
//!   recordable type id i32, format version u32, timestamp f64, instance id u16,
//!   record type u8, compression u8, uncompressed size u32.
//!
//! Every parser here works on untrusted bytes: sizes are checked before use, and a
//! problem is an [`Error`] naming the file, never a panic.

use std::collections::BTreeMap;
use std::fmt;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// 'Visi' 'onRe' ... 'cord': the three magic words of a VRS file header.
const MAGIC1: u32 = u32::from_le_bytes(*b"Visi");
const MAGIC2: u32 = u32::from_le_bytes(*b"onRe");
const MAGIC3: u32 = u32::from_le_bytes(*b"cord");
const MIN_FILE_HEADER: usize = 80;
const MIN_RECORD_HEADER: usize = 32;
/// Recordable type ids reserved by VRS itself.
const INDEX_TYPE_ID: i32 = 1;
const DESCRIPTION_TYPE_ID: i32 = 2;
/// No single record payload may claim more than this (guards allocations on corrupt input).
const MAX_PAYLOAD: usize = 1 << 30;

/// A stream: recordable type id (e.g. 214 for Aria's RGB camera) and instance id.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize)]
pub struct StreamId {
    pub type_id: i32,
    pub instance: u16,
}

impl StreamId {
    pub const ARIA_RGB: StreamId = StreamId { type_id: 214, instance: 1 };
}

impl fmt::Display for StreamId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}-{}", self.type_id, self.instance)
    }
}

/// VRS record types.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum RecordType {
    Undefined,
    State,
    Configuration,
    Data,
    Tags,
    Other(u8),
}

impl RecordType {
    fn from_u8(v: u8) -> Self {
        match v {
            0 => RecordType::Undefined,
            1 => RecordType::State,
            2 => RecordType::Configuration,
            3 => RecordType::Data,
            4 => RecordType::Tags,
            o => RecordType::Other(o),
        }
    }

    /// The name VRS uses in tag keys ("RF:Data:2", "DL:Configuration:2:0").
    pub fn tag_name(&self) -> &'static str {
        match self {
            RecordType::State => "State",
            RecordType::Configuration => "Configuration",
            RecordType::Data => "Data",
            RecordType::Tags => "Tags",
            _ => "Undefined",
        }
    }
}

/// Payload compression.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Compression {
    None,
    Lz4,
    Zstd,
}

/// The fixed part of a VRS file header.
#[derive(Clone, Debug)]
pub struct FileHeader {
    pub creation_id: u64,
    pub file_header_size: u32,
    pub record_header_size: u32,
    pub index_record_offset: i64,
    pub description_record_offset: i64,
    pub first_user_record_offset: i64,
    pub format_version: u32,
}

/// A parsed record header.
#[derive(Clone, Copy, Debug)]
pub struct RecordHeader {
    pub record_size: u32,
    pub previous_record_size: u32,
    pub stream: StreamId,
    pub format_version: u32,
    pub timestamp: f64,
    pub record_type: RecordType,
    pub compression: Compression,
    pub uncompressed_size: u32,
}

/// One entry of the index: where a record is and what it is.
#[derive(Clone, Copy, Debug)]
pub struct RecordInfo {
    pub timestamp: f64,
    pub offset: u64,
    pub size: u32,
    pub stream: StreamId,
    pub record_type: RecordType,
}

/// Tags of one stream: the user's and VRS's own (record formats, data layouts, names).
#[derive(Clone, Debug, Default)]
pub struct StreamTags {
    pub user: BTreeMap<String, String>,
    pub vrs: BTreeMap<String, String>,
}

impl StreamTags {
    /// The stream's original recordable name, e.g. "RGB Camera Class".
    pub fn name(&self) -> Option<&str> {
        self.vrs.get("VRS_Original_Recordable_Name").map(|s| s.as_str())
    }
}

/// Parse the fixed file header from its first bytes.
pub fn parse_file_header(path: &Path, b: &[u8]) -> Result<FileHeader> {
    if b.len() < MIN_FILE_HEADER {
        return Err(Error::bad_file(path, format!("not a VRS file: {} bytes, shorter than a file header", b.len())));
    }
    let mut r = Cursor::new(path, b);
    let m1 = r.u32()?;
    let m2 = r.u32()?;
    let creation_id = r.u64()?;
    let file_header_size = r.u32()?;
    let record_header_size = r.u32()?;
    let index_record_offset = r.i64()?;
    let description_record_offset = r.i64()?;
    let first_user_record_offset = r.i64()?;
    r.skip(24)?;
    let m3 = r.u32()?;
    let format_version = r.u32()?;
    if m1 != MAGIC1 || m2 != MAGIC2 || m3 != MAGIC3 {
        return Err(Error::bad_file(path, "not a VRS file: bad magic numbers"));
    }
    if (file_header_size as usize) < MIN_FILE_HEADER || (record_header_size as usize) < MIN_RECORD_HEADER {
        return Err(Error::bad_file(
            path,
            format!("corrupt VRS header: file header size {file_header_size}, record header size {record_header_size}"),
        ));
    }
    Ok(FileHeader {
        creation_id,
        file_header_size,
        record_header_size,
        index_record_offset,
        description_record_offset,
        first_user_record_offset,
        format_version,
    })
}

/// Parse a record header (at least 32 bytes; larger headers are allowed, extra bytes ignored).
pub fn parse_record_header(path: &Path, b: &[u8]) -> Result<RecordHeader> {
    let mut r = Cursor::new(path, b);
    let record_size = r.u32()?;
    let previous_record_size = r.u32()?;
    let type_id = r.i32()?;
    let format_version = r.u32()?;
    let timestamp = r.f64()?;
    let instance = r.u16()?;
    let record_type = RecordType::from_u8(r.u8()?);
    let compression = match r.u8()? {
        0 => Compression::None,
        1 => Compression::Lz4,
        2 => Compression::Zstd,
        c => return Err(Error::bad_file(path, format!("unknown VRS compression type {c}"))),
    };
    let uncompressed_size = r.u32()?;
    Ok(RecordHeader {
        record_size,
        previous_record_size,
        stream: StreamId { type_id, instance },
        format_version,
        timestamp,
        record_type,
        compression,
        uncompressed_size,
    })
}

/// Parse a description record's payload (format version 2): stream tags then file tags.
pub fn parse_description(
    path: &Path,
    payload: &[u8],
) -> Result<(BTreeMap<StreamId, StreamTags>, BTreeMap<String, String>)> {
    let mut r = Cursor::new(path, payload);
    let n = r.u32()? as usize;
    let mut streams = BTreeMap::new();
    for _ in 0..n {
        let type_id = r.i32()?;
        let instance = r.u16()?;
        let user = r.string_map()?;
        let vrs = r.string_map()?;
        streams.insert(StreamId { type_id, instance }, StreamTags { user, vrs });
    }
    let file_tags = r.string_map()?;
    Ok((streams, file_tags))
}

/// Parse a classic (format version 2) index record payload, already decompressed as
/// needed: stream list, record count, then one 19-byte entry per record. Offsets are
/// accumulated from `first_user_record_offset`; entries past `file_size` are dropped
/// (a truncated file), and the second value tells how many were.
pub fn parse_index(
    path: &Path,
    prelude: &[u8],
    entries: &[u8],
    first_user_record_offset: u64,
    file_size: u64,
) -> Result<(Vec<RecordInfo>, usize)> {
    let _ = prelude;
    if !entries.len().is_multiple_of(19) {
        return Err(Error::bad_file(path, "corrupt VRS index: entry bytes not a multiple of 19"));
    }
    let mut out = Vec::with_capacity(entries.len() / 19);
    let mut offset = first_user_record_offset;
    let mut dropped = 0;
    for (i, e) in entries.chunks_exact(19).enumerate() {
        let mut r = Cursor::new(path, e);
        let timestamp = r.f64()?;
        let size = r.u32()?;
        let record_type = RecordType::from_u8(r.u8()?);
        let type_id = r.i32()?;
        let instance = r.u16()?;
        let next = offset + size as u64;
        if size < MIN_RECORD_HEADER as u32 || next > file_size {
            dropped = entries.len() / 19 - i;
            break;
        }
        out.push(RecordInfo { timestamp, offset, size, stream: StreamId { type_id, instance }, record_type });
        offset = next;
    }
    Ok((out, dropped))
}

/// Decompress a record payload.
pub fn decompress(path: &Path, compression: Compression, data: &[u8], uncompressed_size: usize) -> Result<Vec<u8>> {
    if uncompressed_size > MAX_PAYLOAD {
        return Err(Error::bad_file(path, format!("record claims {uncompressed_size} uncompressed bytes")));
    }
    let mut out = Vec::with_capacity(uncompressed_size);
    match compression {
        Compression::None => return Ok(data.to_vec()),
        Compression::Lz4 => {
            let mut d = lz4_flex::frame::FrameDecoder::new(data);
            d.by_ref()
                .take(uncompressed_size as u64 + 1)
                .read_to_end(&mut out)
                .map_err(|e| Error::bad_file(path, format!("lz4 payload: {e}")))?;
        }
        Compression::Zstd => {
            let mut src = data;
            let mut d = ruzstd::decoding::StreamingDecoder::new(&mut src)
                .map_err(|e| Error::bad_file(path, format!("zstd payload: {e}")))?;
            d.by_ref()
                .take(uncompressed_size as u64 + 1)
                .read_to_end(&mut out)
                .map_err(|e| Error::bad_file(path, format!("zstd payload: {e}")))?;
        }
    }
    if out.len() != uncompressed_size {
        return Err(Error::bad_file(
            path,
            format!("decompressed {} bytes, header says {uncompressed_size}", out.len()),
        ));
    }
    Ok(out)
}

/// What a VRS file is read through: a file, or bytes in memory (tests, fuzzing).
pub trait ReadSeek: Read + Seek + Send {}
impl<T: Read + Seek + Send> ReadSeek for T {}

/// An open VRS file: header, tags and index in memory; records read on demand.
pub struct VrsFile {
    path: PathBuf,
    file: Box<dyn ReadSeek>,
    file_size: u64,
    pub header: FileHeader,
    pub streams: BTreeMap<StreamId, StreamTags>,
    pub file_tags: BTreeMap<String, String>,
    pub index: Vec<RecordInfo>,
    /// True when the index record was missing or unreadable and the index was rebuilt
    /// by walking the records.
    pub index_rebuilt: bool,
    /// Records the index lists beyond the end of the file (truncated recording).
    pub dropped_records: usize,
}

impl fmt::Debug for VrsFile {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("VrsFile")
            .field("path", &self.path)
            .field("records", &self.index.len())
            .field("streams", &self.streams.keys().collect::<Vec<_>>())
            .finish()
    }
}

impl VrsFile {
    pub fn open(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref().to_path_buf();
        let file = File::open(&path).map_err(|e| Error::io(&path, e))?;
        let file_size = file.metadata().map_err(|e| Error::io(&path, e))?.len();
        Self::from_reader(path, Box::new(std::io::BufReader::new(file)), file_size)
    }

    /// Read a VRS file from bytes in memory; `name` is used in error messages.
    pub fn from_bytes(name: impl Into<PathBuf>, bytes: Vec<u8>) -> Result<Self> {
        let size = bytes.len() as u64;
        Self::from_reader(name.into(), Box::new(std::io::Cursor::new(bytes)), size)
    }

    /// Read a VRS file through any seekable reader of `file_size` bytes.
    pub fn from_reader(path: PathBuf, mut file: Box<dyn ReadSeek>, file_size: u64) -> Result<Self> {
        let mut head = vec![0u8; (MIN_FILE_HEADER as u64).min(file_size) as usize];
        file.read_exact(&mut head).map_err(|e| Error::io(&path, e))?;
        let header = parse_file_header(&path, &head)?;
        let mut vrs = VrsFile {
            path,
            file,
            file_size,
            header,
            streams: BTreeMap::new(),
            file_tags: BTreeMap::new(),
            index: Vec::new(),
            index_rebuilt: false,
            dropped_records: 0,
        };
        // Description record.
        let desc_offset = vrs.header.description_record_offset;
        if desc_offset <= 0 {
            return Err(Error::bad_file(&vrs.path, "VRS file has no description record"));
        }
        let (dh, payload) = vrs.read_record_at(desc_offset as u64)?;
        if dh.stream.type_id != DESCRIPTION_TYPE_ID {
            return Err(Error::bad_file(&vrs.path, "VRS description record offset points at another record"));
        }
        let (streams, tags) = parse_description(&vrs.path, &payload)?;
        vrs.streams = streams;
        vrs.file_tags = tags;
        let first_user = if vrs.header.first_user_record_offset > 0 {
            vrs.header.first_user_record_offset as u64
        } else {
            desc_offset as u64 + dh.record_size as u64
        };
        match vrs.read_index(first_user) {
            Ok(()) => {}
            Err(e) => {
                tracing::warn!("{e}; rebuilding the index by walking the records");
                vrs.rebuild_index(first_user)?;
            }
        }
        Ok(vrs)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn file_size(&self) -> u64 {
        self.file_size
    }

    fn read_exact_at(&mut self, offset: u64, len: usize) -> Result<Vec<u8>> {
        if offset.checked_add(len as u64).is_none_or(|end| end > self.file_size) {
            return Err(Error::bad_file(
                &self.path,
                format!("truncated: {len} bytes at offset {offset} run past the end ({} bytes)", self.file_size),
            ));
        }
        self.file.seek(SeekFrom::Start(offset)).map_err(|e| Error::io(&self.path, e))?;
        let mut buf = vec![0u8; len];
        self.file.read_exact(&mut buf).map_err(|e| Error::io(&self.path, e))?;
        Ok(buf)
    }

    /// Read the record header at `offset` and its raw (possibly compressed) payload.
    fn read_raw_at(&mut self, offset: u64) -> Result<(RecordHeader, Vec<u8>)> {
        let hs = self.header.record_header_size as usize;
        let hb = self.read_exact_at(offset, hs)?;
        let h = parse_record_header(&self.path, &hb)?;
        let size = h.record_size as usize;
        if size < hs || size - hs > MAX_PAYLOAD {
            return Err(Error::bad_file(&self.path, format!("corrupt record at offset {offset}: size {size}")));
        }
        let payload = self.read_exact_at(offset + hs as u64, size - hs)?;
        Ok((h, payload))
    }

    /// Read the record at `offset`, decompressing its payload.
    pub fn read_record_at(&mut self, offset: u64) -> Result<(RecordHeader, Vec<u8>)> {
        let (h, raw) = self.read_raw_at(offset)?;
        let payload = if h.compression == Compression::None {
            raw
        } else {
            decompress(&self.path, h.compression, &raw, h.uncompressed_size as usize)
                .map_err(|e| Error::bad_file(&self.path, format!("record at offset {offset}: {e}")))?
        };
        Ok((h, payload))
    }

    fn read_index(&mut self, first_user: u64) -> Result<()> {
        let off = self.header.index_record_offset;
        if off <= 0 {
            return Err(Error::bad_file(&self.path, "VRS file has no index (interrupted recording?)"));
        }
        let (h, raw) = self.read_raw_at(off as u64)?;
        if h.stream.type_id != INDEX_TYPE_ID {
            return Err(Error::bad_file(&self.path, "VRS index offset points at another record"));
        }
        if h.format_version != 2 {
            return Err(Error::bad_file(&self.path, format!("unsupported VRS index format {}", h.format_version)));
        }
        // Prelude (stream count, streams, record count) is never compressed.
        let mut r = Cursor::new(&self.path, &raw);
        let n_streams = r.u32()? as usize;
        r.skip(n_streams.checked_mul(6).ok_or_else(|| Error::bad_file(&self.path, "corrupt index"))?)?;
        let n_records = r.u32()? as usize;
        let prelude_len = r.pos;
        let body = &raw[prelude_len..];
        let want = n_records
            .checked_mul(19)
            .filter(|&w| w <= MAX_PAYLOAD)
            .ok_or_else(|| Error::bad_file(&self.path, "corrupt index: record count"))?;
        let entries = if h.uncompressed_size > 0 {
            // Only zstd is used for indexes.
            decompress(&self.path, Compression::Zstd, body, want)?
        } else {
            if body.len() < want {
                return Err(Error::bad_file(&self.path, "corrupt index: fewer entries than announced"));
            }
            body[..want].to_vec()
        };
        let (index, dropped) = parse_index(&self.path, &raw[..prelude_len], &entries, first_user, self.file_size)?;
        if dropped > 0 {
            tracing::warn!("{}: {dropped} indexed records lie beyond the end of the file", self.path.display());
        }
        self.index = index;
        self.dropped_records = dropped;
        Ok(())
    }

    /// Walk records from the first user record, following record sizes, until the end
    /// or the first record that does not fit (a truncated file).
    fn rebuild_index(&mut self, first_user: u64) -> Result<()> {
        let hs = self.header.record_header_size as u64;
        let mut off = first_user;
        let mut index = Vec::new();
        while off + hs <= self.file_size {
            let hb = self.read_exact_at(off, hs as usize)?;
            let h = parse_record_header(&self.path, &hb)?;
            if (h.record_size as u64) < hs || off + h.record_size as u64 > self.file_size {
                tracing::warn!("{}: record at offset {off} is truncated; stopping there", self.path.display());
                break;
            }
            if h.stream.type_id != INDEX_TYPE_ID && h.stream.type_id != DESCRIPTION_TYPE_ID {
                index.push(RecordInfo {
                    timestamp: h.timestamp,
                    offset: off,
                    size: h.record_size,
                    stream: h.stream,
                    record_type: h.record_type,
                });
            }
            off += h.record_size as u64;
        }
        index.sort_by(|a, b| a.timestamp.total_cmp(&b.timestamp).then(a.offset.cmp(&b.offset)));
        self.index = index;
        self.index_rebuilt = true;
        Ok(())
    }

    /// Records of one stream and type, in index (time) order.
    pub fn records(&self, stream: StreamId, record_type: RecordType) -> Vec<RecordInfo> {
        self.index.iter().filter(|r| r.stream == stream && r.record_type == record_type).copied().collect()
    }

    /// Count of records per stream.
    pub fn record_counts(&self) -> BTreeMap<StreamId, usize> {
        let mut m = BTreeMap::new();
        for r in &self.index {
            *m.entry(r.stream).or_insert(0) += 1;
        }
        m
    }

    /// The content-block layout declared for a stream's records of a given type and
    /// format version ("RF:Data:2" -> "data_layout/size=84+image/jpg").
    pub fn record_format(&self, stream: StreamId, rt: RecordType, version: u32) -> Option<RecordFormat> {
        let tags = self.streams.get(&stream)?;
        let s = tags.vrs.get(&format!("RF:{}:{version}", rt.tag_name()))?;
        let mut fmt = RecordFormat::parse(s);
        for (i, b) in fmt.blocks.iter_mut().enumerate() {
            if b.kind == BlockKind::DataLayout {
                if let Some(json) = tags.vrs.get(&format!("DL:{}:{version}:{i}", rt.tag_name())) {
                    b.layout = DataLayout::from_json(json).ok();
                }
            }
        }
        Some(fmt)
    }

    /// Read one record and split it into content blocks following its stream's record format.
    pub fn read_blocks(&mut self, info: &RecordInfo) -> Result<RecordContent> {
        let (h, payload) = self.read_record_at(info.offset)?;
        let fmt = self.record_format(h.stream, h.record_type, h.format_version).ok_or_else(|| {
            Error::bad_file(
                &self.path,
                format!("stream {} has no record format for {:?} v{}", h.stream, h.record_type, h.format_version),
            )
        })?;
        let blocks = fmt.split(&self.path, &payload)?;
        Ok(RecordContent { header: h, payload, blocks })
    }
}

/// What kind of content a block holds.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum BlockKind {
    DataLayout,
    Image(String),
    Other(String),
}

/// One content block of a record format.
#[derive(Clone, Debug)]
pub struct BlockFormat {
    pub kind: BlockKind,
    pub size: Option<usize>,
    pub layout: Option<DataLayout>,
}

/// A record format: a sequence of content blocks.
#[derive(Clone, Debug)]
pub struct RecordFormat {
    pub blocks: Vec<BlockFormat>,
}

impl RecordFormat {
    /// Parse e.g. "data_layout/size=84+image/jpg".
    pub fn parse(s: &str) -> Self {
        let blocks = s
            .split('+')
            .filter(|b| !b.is_empty())
            .map(|b| {
                let mut parts = b.split('/');
                let head = parts.next().unwrap_or("");
                let mut size = None;
                let mut rest = Vec::new();
                for p in parts {
                    if let Some(v) = p.strip_prefix("size=") {
                        size = v.parse().ok();
                    } else {
                        rest.push(p);
                    }
                }
                let kind = match head {
                    "data_layout" => BlockKind::DataLayout,
                    "image" => BlockKind::Image(rest.first().copied().unwrap_or("").to_string()),
                    other => BlockKind::Other(other.to_string()),
                };
                BlockFormat { kind, size, layout: None }
            })
            .collect();
        RecordFormat { blocks }
    }

    /// Byte ranges of each block within a payload.
    pub fn split(&self, path: &Path, payload: &[u8]) -> Result<Vec<(BlockKind, std::ops::Range<usize>)>> {
        let mut out = Vec::new();
        let mut pos = 0usize;
        for (i, b) in self.blocks.iter().enumerate() {
            let last = i + 1 == self.blocks.len();
            let size = match (b.size, &b.layout) {
                (Some(s), _) => s,
                (None, _) if last => payload.len() - pos,
                (None, Some(l)) => l.block_size(path, &payload[pos..])?,
                (None, None) => {
                    return Err(Error::bad_file(path, "record block of unknown size before the last block"));
                }
            };
            let end = pos.checked_add(size).filter(|&e| e <= payload.len()).ok_or_else(|| {
                Error::bad_file(path, format!("record payload of {} bytes too short for its blocks", payload.len()))
            })?;
            out.push((b.kind.clone(), pos..end));
            pos = end;
        }
        Ok(out)
    }
}

/// A record's decompressed payload split into its content blocks.
#[derive(Clone, Debug)]
pub struct RecordContent {
    pub header: RecordHeader,
    pub payload: Vec<u8>,
    pub blocks: Vec<(BlockKind, std::ops::Range<usize>)>,
}

impl RecordContent {
    pub fn block(&self, pred: impl Fn(&BlockKind) -> bool) -> Option<&[u8]> {
        self.blocks.iter().find(|(k, _)| pred(k)).map(|(_, r)| &self.payload[r.clone()])
    }
}

/// One piece of a DataLayout: a fixed-size value at an offset, or a variable-size piece
/// (string, vector) at an index into the variable-size section.
#[derive(Clone, Debug)]
pub struct DataPiece {
    pub name: String,
    pub type_name: String,
    pub offset: Option<usize>,
    pub var_index: Option<usize>,
    pub size: Option<usize>,
}

/// VRS DataLayout metadata (from a stream's "DL:..." tag): names, types and where each
/// value sits in the block.
#[derive(Clone, Debug)]
pub struct DataLayout {
    pub pieces: Vec<DataPiece>,
    /// Size of the fixed part, when every fixed piece's type is known.
    pub fixed_size: Option<usize>,
    pub var_count: usize,
}

fn scalar_size(t: &str) -> Option<usize> {
    Some(match t {
        "int8_t" | "uint8_t" | "char" | "Bool" => 1,
        "int16_t" | "uint16_t" => 2,
        "int32_t" | "uint32_t" | "float" => 4,
        "int64_t" | "uint64_t" | "double" => 8,
        "Point2Df" => 8,
        "Point3Df" => 12,
        "Point4Df" => 16,
        "Point2Dd" => 16,
        "Point3Dd" => 24,
        "Point4Dd" => 32,
        "Point2Di" => 8,
        "Point3Di" => 12,
        "Point4Di" => 16,
        "Matrix2Df" => 16,
        "Matrix3Df" => 36,
        "Matrix4Df" => 64,
        "Matrix2Dd" => 32,
        "Matrix3Dd" => 72,
        "Matrix4Dd" => 128,
        _ => return None,
    })
}

impl DataLayout {
    pub fn from_json(s: &str) -> std::result::Result<Self, String> {
        let v: serde_json::Value = serde_json::from_str(s).map_err(|e| e.to_string())?;
        let arr = v.get("data_layout").and_then(|a| a.as_array()).ok_or("no data_layout array")?;
        let mut pieces = Vec::new();
        let mut fixed: Option<usize> = Some(0);
        let mut var_count = 0;
        for p in arr {
            let name = p.get("name").and_then(|n| n.as_str()).unwrap_or("").to_string();
            let type_name = p.get("type").and_then(|n| n.as_str()).unwrap_or("").to_string();
            let offset = p.get("offset").and_then(|n| n.as_u64()).map(|n| n as usize);
            let var_index = p.get("index").and_then(|n| n.as_u64()).map(|n| n as usize);
            let inner = type_name.split_once('<').map(|(_, r)| r.trim_end_matches('>')).unwrap_or("");
            let size = if type_name.starts_with("DataPieceValue") {
                scalar_size(inner)
            } else if type_name.starts_with("DataPieceArray") {
                let count = p.get("size").and_then(|n| n.as_u64()).map(|n| n as usize);
                scalar_size(inner).zip(count).map(|(a, b)| a * b)
            } else {
                None
            };
            if let Some(off) = offset {
                fixed = match (fixed, size) {
                    (Some(f), Some(s)) => Some(f.max(off + s)),
                    _ => None,
                };
            }
            if var_index.is_some() {
                var_count += 1;
            }
            pieces.push(DataPiece { name, type_name, offset, var_index, size });
        }
        Ok(DataLayout { pieces, fixed_size: fixed, var_count })
    }

    fn piece(&self, name: &str) -> Option<&DataPiece> {
        self.pieces.iter().find(|p| p.name == name)
    }

    /// Size of a whole block (fixed part, var index, var data) from its start bytes.
    pub fn block_size(&self, path: &Path, b: &[u8]) -> Result<usize> {
        let fixed =
            self.fixed_size.ok_or_else(|| Error::bad_file(path, "DataLayout with a fixed piece of unknown type"))?;
        if self.var_count == 0 {
            return Ok(fixed);
        }
        let idx_end = fixed + 8 * self.var_count;
        if b.len() < idx_end {
            return Err(Error::bad_file(path, "DataLayout block shorter than its index"));
        }
        let mut end = 0usize;
        for k in 0..self.var_count {
            let e = &b[fixed + 8 * k..fixed + 8 * k + 8];
            let off = u32::from_le_bytes([e[0], e[1], e[2], e[3]]) as usize;
            let len = u32::from_le_bytes([e[4], e[5], e[6], e[7]]) as usize;
            end = end.max(off.saturating_add(len));
        }
        Ok(idx_end.saturating_add(end))
    }

    fn fixed_bytes<'a>(&self, block: &'a [u8], name: &str, n: usize) -> Option<&'a [u8]> {
        let p = self.piece(name)?;
        let off = p.offset?;
        if p.size? < n {
            return None;
        }
        block.get(off..off + n)
    }

    pub fn get_i64(&self, block: &[u8], name: &str) -> Option<i64> {
        let b = self.fixed_bytes(block, name, 8)?;
        Some(i64::from_le_bytes(b.try_into().ok()?))
    }

    pub fn get_u64(&self, block: &[u8], name: &str) -> Option<u64> {
        let b = self.fixed_bytes(block, name, 8)?;
        Some(u64::from_le_bytes(b.try_into().ok()?))
    }

    pub fn get_u32(&self, block: &[u8], name: &str) -> Option<u32> {
        let b = self.fixed_bytes(block, name, 4)?;
        Some(u32::from_le_bytes(b.try_into().ok()?))
    }

    pub fn get_f64(&self, block: &[u8], name: &str) -> Option<f64> {
        let b = self.fixed_bytes(block, name, 8)?;
        Some(f64::from_le_bytes(b.try_into().ok()?))
    }

    /// A variable-size string piece.
    pub fn get_string(&self, block: &[u8], name: &str) -> Option<String> {
        let p = self.piece(name)?;
        let k = p.var_index?;
        let fixed = self.fixed_size?;
        let e = block.get(fixed + 8 * k..fixed + 8 * k + 8)?;
        let off = u32::from_le_bytes([e[0], e[1], e[2], e[3]]) as usize;
        let len = u32::from_le_bytes([e[4], e[5], e[6], e[7]]) as usize;
        let start = fixed + 8 * self.var_count + off;
        let bytes = block.get(start..start.checked_add(len)?)?;
        Some(String::from_utf8_lossy(bytes).into_owned())
    }
}

/// A bounds-checked little-endian reader over bytes that names the file in its errors.
pub(crate) struct Cursor<'a> {
    path: &'a Path,
    b: &'a [u8],
    pub pos: usize,
}

impl<'a> Cursor<'a> {
    pub fn new(path: &'a Path, b: &'a [u8]) -> Self {
        Cursor { path, b, pos: 0 }
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.b.len()).ok_or_else(|| {
            Error::bad_file(
                self.path,
                format!("truncated: wanted {n} bytes at offset {} of {}", self.pos, self.b.len()),
            )
        })?;
        let s = &self.b[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn arr<const N: usize>(&mut self) -> Result<[u8; N]> {
        let s = self.take(N)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        Ok(a)
    }

    pub fn skip(&mut self, n: usize) -> Result<()> {
        self.take(n).map(|_| ())
    }
    pub fn u8(&mut self) -> Result<u8> {
        Ok(self.arr::<1>()?[0])
    }
    pub fn u16(&mut self) -> Result<u16> {
        Ok(u16::from_le_bytes(self.arr()?))
    }
    pub fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(self.arr()?))
    }
    pub fn i32(&mut self) -> Result<i32> {
        Ok(i32::from_le_bytes(self.arr()?))
    }
    pub fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.arr()?))
    }
    pub fn i64(&mut self) -> Result<i64> {
        Ok(i64::from_le_bytes(self.arr()?))
    }
    pub fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_le_bytes(self.arr()?))
    }
    fn string(&mut self) -> Result<String> {
        let n = self.u32()? as usize;
        let s = self.take(n)?;
        Ok(String::from_utf8_lossy(s).into_owned())
    }
    fn string_map(&mut self) -> Result<BTreeMap<String, String>> {
        let n = self.u32()? as usize;
        let mut m = BTreeMap::new();
        for _ in 0..n {
            let k = self.string()?;
            let v = self.string()?;
            m.insert(k, v);
        }
        Ok(m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn record_format_parses_blocks() {
        let f = RecordFormat::parse("data_layout/size=84+image/jpg");
        assert_eq!(f.blocks.len(), 2);
        assert_eq!(f.blocks[0].kind, BlockKind::DataLayout);
        assert_eq!(f.blocks[0].size, Some(84));
        assert_eq!(f.blocks[1].kind, BlockKind::Image("jpg".into()));
        let p = Path::new("x");
        let payload = vec![0u8; 100];
        let s = f.split(p, &payload).unwrap();
        assert_eq!(s[0].1, 0..84);
        assert_eq!(s[1].1, 84..100);
        assert!(f.split(p, &payload[..50]).is_err());
    }

    #[test]
    fn data_layout_reads_values_and_strings() {
        let json = r#"{"data_layout":[{"name":"a","type":"DataPieceValue<uint32_t>","offset":0},
            {"name":"t","type":"DataPieceValue<int64_t>","offset":4},
            {"name":"s","type":"DataPieceString","index":0},{"name":"u","type":"DataPieceString","index":1}]}"#;
        let l = DataLayout::from_json(json).unwrap();
        assert_eq!(l.fixed_size, Some(12));
        let mut b = Vec::new();
        b.extend_from_slice(&7u32.to_le_bytes());
        b.extend_from_slice(&(-5i64).to_le_bytes());
        b.extend_from_slice(&0u32.to_le_bytes());
        b.extend_from_slice(&3u32.to_le_bytes());
        b.extend_from_slice(&3u32.to_le_bytes());
        b.extend_from_slice(&2u32.to_le_bytes());
        b.extend_from_slice(b"abcde");
        assert_eq!(l.get_u32(&b, "a"), Some(7));
        assert_eq!(l.get_i64(&b, "t"), Some(-5));
        assert_eq!(l.get_string(&b, "s").as_deref(), Some("abc"));
        assert_eq!(l.get_string(&b, "u").as_deref(), Some("de"));
        assert_eq!(l.block_size(Path::new("x"), &b).unwrap(), b.len());
        assert_eq!(l.get_u32(&b[..2], "a"), None);
    }

    #[test]
    fn bad_magic_is_an_error_naming_the_file() {
        let e = parse_file_header(Path::new("some.vrs"), &[0u8; 80]).unwrap_err();
        assert!(e.to_string().contains("some.vrs"), "{e}");
    }
}
