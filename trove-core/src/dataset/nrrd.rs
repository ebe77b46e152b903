//! A small NRRD reader (<http://teem.sourceforge.net/nrrd/format.html>), for scalar volumes
//! of 1 to 3 dimensions, raw or gzip, with an attached or a detached header.
//!
//! No maintained NRRD crate exists, and the subset volume renderers meet is small, so it is
//! written here. What is read: the magic `NRRD0001`..`NRRD0005`, `type`, `dimension`,
//! `sizes`, `endian`, `encoding`, `data file` (one file), `byte skip` and `line skip`.
//! Everything else (spacings, space directions, kinds, comments, `key:=value` pairs) does not
//! change which number sits at which voxel and is ignored. Anything that would need more
//! (other encodings, 64-bit integers, multi-file data, data at the end of a file) is refused
//! with a message naming the file and the field, never guessed.
//!
//! Sizes are checked when the header is opened: for gzip data that means inflating and
//! counting the stream once, so a wrong header is an error at scene load.

use std::fs::File;
use std::io::{BufRead, BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use super::error::DatasetError;
use super::raw::{self, StoredType};
use super::{ChannelSource, Dims, Encoding, Endian, VoxelType};

/// One channel described by a file header (NRRD, NIfTI): its dims, its type once loaded,
/// and where its voxels come from. Sizes were already checked against the header.
#[derive(Clone, Debug)]
pub struct FileChannel {
    /// Voxels per axis (missing trailing axes are 1).
    pub dims: Dims,
    /// Storage type once loaded (types TROVE does not store natively become f32).
    pub ty: VoxelType,
    /// Where the voxels come from.
    pub source: ChannelSource,
}

/// The header must end (blank line or end of file) within this many bytes; it keeps a binary
/// file that is not NRRD from being read whole in search of one.
const MAX_HEADER: usize = 1 << 20;

/// Reads the header of `path` (`.nrrd` or `.nhdr`) and checks the data's size against it. A
/// detached header's `data file` is read relative to the header's folder. (The renderer
/// goes through [`open_in`] from a catalog; the readers' tests use this.)
#[cfg(test)]
pub(crate) fn open(path: &Path) -> Result<FileChannel, DatasetError> {
    open_in(path, &|_, joined| Ok(joined))
}

/// As [`open`], with `locate` deciding where a detached header's data file is: it gets the
/// `data file` value as written and that value joined to the header's folder, and returns
/// the path to read (a sandboxed catalog canonicalises it and refuses one outside its root).
pub(crate) fn open_in(path: &Path, locate: &DataFileLocator<'_>) -> Result<FileChannel, DatasetError> {
    let (lines, attached_offset) = read_header(path)?;
    let fields = Fields::parse(path, &lines)?;
    let layout = fields.layout()?;
    let (data_path, offset) = fields.data_location(attached_offset, layout.encoding, locate)?;
    let source = raw::open_with(&data_path, offset, layout.encoding, layout.stored, layout.endian, layout.dims)
        .map_err(|e| match e {
            DatasetError::SizeMismatch { path: p, expected, actual, what } => DatasetError::SizeMismatch {
                path: p,
                expected,
                actual,
                what: format!("{what} (fields `sizes` and `type` of {})", path.display()),
            },
            e => e,
        })?;
    Ok(FileChannel { dims: layout.dims, ty: layout.stored.loaded_type(), source })
}

/// Where a detached header's data file is: `(value as written, value joined to the header's
/// folder) → path to read`.
pub(crate) type DataFileLocator<'a> = dyn Fn(&str, PathBuf) -> Result<PathBuf, DatasetError> + 'a;

/// What the header says about the numbers: which one sits at which voxel.
struct Layout {
    dims: Dims,
    stored: StoredType,
    endian: Endian,
    encoding: Encoding,
}

/// The header's lines (magic first), and where attached data would begin: just after the
/// blank line ending the header, `None` if the file ends first (a detached header).
fn read_header(path: &Path) -> Result<(Vec<String>, Option<u64>), DatasetError> {
    let file = File::open(path).map_err(|e| DatasetError::io(path, e))?;
    let mut buf = Vec::new();
    file.take(MAX_HEADER as u64 + 1).read_to_end(&mut buf).map_err(|e| DatasetError::io(path, e))?;
    let mut lines = Vec::new();
    let mut pos = 0;
    while pos < buf.len() {
        let (line, next) = match buf[pos..].iter().position(|&b| b == b'\n') {
            Some(n) => (&buf[pos..pos + n], pos + n + 1),
            None if buf.len() > MAX_HEADER => break,
            None => (&buf[pos..], buf.len()),
        };
        let line = line.strip_suffix(b"\r").unwrap_or(line);
        if lines.is_empty() {
            check_magic(path, line)?;
        } else if line.is_empty() {
            return Ok((lines, Some(next as u64)));
        }
        lines.push(String::from_utf8_lossy(line).into_owned());
        pos = next;
    }
    if buf.len() > MAX_HEADER {
        return Err(DatasetError::format(path, "no blank line ends the NRRD header within its first MiB"));
    }
    if lines.is_empty() {
        return Err(DatasetError::format(path, "empty file; expected a NRRD header starting with `NRRD000N`"));
    }
    Ok((lines, None))
}

fn check_magic(path: &Path, line: &[u8]) -> Result<(), DatasetError> {
    match line {
        [b'N', b'R', b'R', b'D', b'0', b'0', b'0', v] if (b'1'..=b'5').contains(v) => Ok(()),
        [b'N', b'R', b'R', b'D', ..] => Err(DatasetError::format(
            path,
            format!("unsupported NRRD version `{}` (NRRD0001 to NRRD0005 are read)", String::from_utf8_lossy(line)),
        )),
        _ => Err(DatasetError::format(path, "not a NRRD file: it does not start with `NRRD000N`")),
    }
}

/// The header's fields by normalised name (lower case, `datafile` → `data file`, ...).
struct Fields<'a> {
    path: &'a Path,
    fields: Vec<(String, String)>,
}

impl<'a> Fields<'a> {
    fn parse(path: &'a Path, lines: &[String]) -> Result<Fields<'a>, DatasetError> {
        let mut fields: Vec<(String, String)> = Vec::new();
        for line in lines.iter().skip(1) {
            if line.starts_with('#') || line.trim().is_empty() {
                continue;
            }
            let Some(colon) = line.find(':') else {
                return Err(DatasetError::format(path, format!("header line `{line}` is not `field: value`")));
            };
            let rest = &line[colon + 1..];
            if rest.starts_with('=') {
                continue; // key:=value pairs carry no layout information
            }
            let name = line[..colon].trim().to_ascii_lowercase();
            let name = match name.as_str() {
                "datafile" => "data file".to_string(),
                "byteskip" => "byte skip".to_string(),
                "lineskip" => "line skip".to_string(),
                _ => name,
            };
            if fields.iter().any(|(n, _)| *n == name) {
                return Err(DatasetError::format(path, format!("field `{name}` is given twice")));
            }
            let value = rest.trim().to_string();
            // `data file: LIST` is followed by file names, not fields.
            let list = name == "data file" && (value == "LIST" || value.starts_with("LIST "));
            fields.push((name, value));
            if list {
                break;
            }
        }
        Ok(Fields { path, fields })
    }

    /// A refusal of field `field`.
    fn error(&self, field: &str, message: impl std::fmt::Display) -> DatasetError {
        DatasetError::format(self.path, format!("field `{field}`: {message}"))
    }

    /// `dimension`, `sizes`, `type`, `endian` and `encoding`.
    fn layout(&self) -> Result<Layout, DatasetError> {
        let dims = self.dims()?;
        let ty_text = self.required("type")?;
        let stored = parse_type(ty_text).map_err(|m| self.error("type", m))?;
        let endian = match self.get("endian") {
            Some(e) => match e.to_ascii_lowercase().as_str() {
                "little" => Endian::Little,
                "big" => Endian::Big,
                other => return Err(self.error("endian", format!("`{other}` is neither `little` nor `big`"))),
            },
            None if stored.bytes_per_voxel().is_some_and(|b| b > 1) => {
                return Err(DatasetError::format(
                    self.path,
                    format!(
                        "missing field `endian`, which NRRD requires for type `{ty_text}` (say `endian: little` or \
                         `endian: big`)"
                    ),
                ));
            }
            None => Endian::Little,
        };
        let encoding = match self.required("encoding")?.to_ascii_lowercase().as_str() {
            "raw" => Encoding::Raw,
            "gzip" | "gz" => Encoding::Gzip,
            other @ ("ascii" | "text" | "txt" | "hex" | "bzip2" | "bz2" | "zrl" | "zstd") => {
                return Err(self.error("encoding", format!("`{other}` is not supported; TROVE reads `raw` and `gzip`")));
            }
            other => {
                return Err(self.error("encoding", format!("unknown encoding `{other}`; TROVE reads `raw` and `gzip`")))
            }
        };
        Ok(Layout { dims, stored, endian, encoding })
    }

    /// `dimension` and `sizes`: 1 to 3 axes, missing trailing axes of size 1.
    fn dims(&self) -> Result<Dims, DatasetError> {
        let text = self.required("dimension")?;
        let dimension: usize =
            text.parse().map_err(|_| self.error("dimension", format!("`{text}` is not a whole number")))?;
        if !(1..=3).contains(&dimension) {
            return Err(self.error(
                "dimension",
                format!("{dimension} is not supported; TROVE reads scalar volumes of 1 to 3 dimensions"),
            ));
        }
        let mut sizes = Vec::new();
        for s in self.required("sizes")?.split_whitespace() {
            sizes.push(s.parse::<u64>().map_err(|_| self.error("sizes", format!("`{s}` is not a whole number")))?);
        }
        if sizes.len() != dimension {
            return Err(self.error("sizes", format!("gives {} sizes but `dimension` is {dimension}", sizes.len())));
        }
        sizes.resize(3, 1);
        Dims::new([sizes[0], sizes[1], sizes[2]]).map_err(|source| DatasetError::Dims {
            path: self.path.to_path_buf(),
            field: "field `sizes`",
            source,
        })
    }

    /// The file holding the data and the offset of the first voxel in it: `data file` (or
    /// the header's own file after its blank line), then `line skip` and `byte skip`.
    fn data_location(
        &self,
        attached_offset: Option<u64>,
        encoding: Encoding,
        locate: &DataFileLocator<'_>,
    ) -> Result<(PathBuf, u64), DatasetError> {
        let (data_path, mut offset) =
            match self.get("data file") {
                Some(name) => (locate(name, data_file(self.path, name).map_err(|m| self.error("data file", m))?)?, 0),
                None => match attached_offset {
                    Some(off) => (self.path.to_path_buf(), off),
                    None => return Err(DatasetError::format(
                        self.path,
                        "the header has no `data file` field and no blank line after which attached data would begin",
                    )),
                },
            };
        if let Some(text) = self.get("line skip") {
            let n: u64 =
                text.parse().map_err(|_| self.error("line skip", format!("`{text}` is not a whole number ≥ 0")))?;
            offset = skip_lines(&data_path, offset, n).map_err(|e| match e {
                DatasetError::Format { path, message } => {
                    DatasetError::format(path, format!("field `line skip` of the header: {message}"))
                }
                e => e,
            })?;
        }
        if let Some(text) = self.get("byte skip") {
            let n: i64 =
                text.parse().map_err(|_| self.error("byte skip", format!("`{text}` is not a whole number")))?;
            if n < 0 {
                return Err(self.error(
                    "byte skip",
                    format!("{n} (data at the end of the file) is not supported; give the exact offset"),
                ));
            }
            if n > 0 && encoding == Encoding::Gzip {
                return Err(self.error("byte skip", "skipping decompressed bytes of gzip data is not supported"));
            }
            offset += n as u64;
        }
        Ok((data_path, offset))
    }

    fn get(&self, name: &str) -> Option<&str> {
        self.fields.iter().find(|(n, _)| n == name).map(|(_, v)| v.as_str())
    }

    fn required(&self, name: &str) -> Result<&str, DatasetError> {
        self.get(name).ok_or_else(|| DatasetError::format(self.path, format!("missing required field `{name}`")))
    }
}

/// Why a `type` value is refused (the caller names the file and field).
#[derive(Debug, PartialEq, Eq)]
enum TypeProblem {
    SixtyFourBit(String),
    Block,
    Unknown(String),
}

impl std::fmt::Display for TypeProblem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TypeProblem::SixtyFourBit(text) => write!(
                f,
                "64-bit integers (`{text}`) are not supported: voxels are read as f32 and most 64-bit values would \
                 not survive; convert the data to 32 bits or float"
            ),
            TypeProblem::Block => f.write_str("`block` data is not supported"),
            TypeProblem::Unknown(text) => write!(f, "unknown type `{text}`"),
        }
    }
}

/// Every spelling NRRD allows for each type, case and spacing insensitive.
fn parse_type(text: &str) -> Result<StoredType, TypeProblem> {
    let t = text.split_whitespace().collect::<Vec<_>>().join(" ").to_ascii_lowercase();
    Ok(match t.as_str() {
        "signed char" | "int8" | "int8_t" => StoredType::I8,
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => StoredType::U8,
        "short" | "short int" | "signed short" | "signed short int" | "int16" | "int16_t" => StoredType::I16,
        "ushort" | "unsigned short" | "unsigned short int" | "uint16" | "uint16_t" => StoredType::U16,
        "int" | "signed int" | "int32" | "int32_t" => StoredType::I32,
        "uint" | "unsigned int" | "uint32" | "uint32_t" => StoredType::U32,
        "float" => StoredType::F32,
        "double" => StoredType::F64,
        "longlong"
        | "long long"
        | "long long int"
        | "signed long long"
        | "signed long long int"
        | "int64"
        | "int64_t"
        | "ulonglong"
        | "unsigned long long"
        | "unsigned long long int"
        | "uint64"
        | "uint64_t" => return Err(TypeProblem::SixtyFourBit(text.to_string())),
        "block" => return Err(TypeProblem::Block),
        _ => return Err(TypeProblem::Unknown(text.to_string())),
    })
}

/// Why a `data file` value is refused (the caller names the file and field).
#[derive(Debug)]
enum DataFileProblem {
    List,
    Pattern(String),
    Empty,
}

impl std::fmt::Display for DataFileProblem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DataFileProblem::List => {
                f.write_str("`LIST` (data in several files) is not supported; concatenate them into one file")
            }
            DataFileProblem::Pattern(value) => {
                write!(f, "`{value}` names several files by a pattern, which is not supported; concatenate them")
            }
            DataFileProblem::Empty => f.write_str("no file name given"),
        }
    }
}

/// The single data file named by `data file`, relative to the header's folder.
fn data_file(header: &Path, value: &str) -> Result<PathBuf, DataFileProblem> {
    if value == "LIST" || value.starts_with("LIST ") {
        return Err(DataFileProblem::List);
    }
    if value.contains('%') && value.split_whitespace().count() > 1 {
        return Err(DataFileProblem::Pattern(value.to_string()));
    }
    if value.is_empty() {
        return Err(DataFileProblem::Empty);
    }
    let dir = header.parent().unwrap_or_else(|| Path::new(""));
    Ok(dir.join(value))
}

/// The offset just past `n` more newlines in `path`, starting at `from`.
fn skip_lines(path: &Path, from: u64, n: u64) -> Result<u64, DatasetError> {
    let mut file = File::open(path).map_err(|e| DatasetError::io(path, e))?;
    file.seek(SeekFrom::Start(from)).map_err(|e| DatasetError::io(path, e))?;
    let mut reader = BufReader::new(file);
    let mut offset = from;
    let mut skipped = 0;
    while skipped < n {
        let buf = reader.fill_buf().map_err(|e| DatasetError::io(path, e))?;
        if buf.is_empty() {
            return Err(DatasetError::format(path, format!("the file ends after {skipped} of the {n} lines to skip")));
        }
        let (used, found) = match buf.iter().position(|&b| b == b'\n') {
            Some(i) => (i + 1, true),
            None => (buf.len(), false),
        };
        reader.consume(used);
        offset += used as u64;
        skipped += found as u64;
    }
    Ok(offset)
}

#[cfg(test)]
mod tests {
    use super::super::raw::testutil::{data_dir, gzip, TempFile};
    use super::super::DataFile;
    use super::*;

    fn file_source(fc: &FileChannel) -> (&Path, u64, Encoding, StoredType, Endian) {
        match &fc.source {
            ChannelSource::File { file: DataFile::Local(path), offset, encoding, stored, endian } => {
                (path.as_path(), *offset, *encoding, *stored, *endian)
            }
            s => panic!("not a file source: {s:?}"),
        }
    }

    #[test]
    fn cthead_u16_little_endian_detached() {
        let Some(dir) = data_dir() else { return };
        let fc = open(&dir.join("cthead_256x256x113_uint16_le.nhdr")).unwrap();
        assert_eq!(fc.dims.as_array(), [256, 256, 113]);
        assert_eq!(fc.ty, VoxelType::U16);
        let (path, offset, enc, stored, endian) = file_source(&fc);
        assert_eq!(path, dir.join("cthead_256x256x113_uint16_le.raw"));
        assert_eq!((offset, enc, stored, endian), (0, Encoding::Raw, StoredType::U16, Endian::Little));
        let ch = fc.source.load(fc.dims).unwrap();
        assert!(ch.is_mapped());
        let bytes = std::fs::read(path).unwrap();
        let mut nonzero = 0;
        for (i, j, k) in [(128, 128, 56), (100, 80, 30), (0, 0, 0), (255, 255, 112), (60, 190, 90), (128, 40, 10)] {
            let idx = fc.dims.index(i, j, k);
            let expected = u16::from_le_bytes([bytes[2 * idx], bytes[2 * idx + 1]]);
            nonzero += (expected != 0) as u32;
            assert_eq!(ch.value(idx), expected as f32, "voxel ({i}, {j}, {k})");
        }
        assert!(nonzero >= 2, "the chosen voxels should include some tissue");
        // PROVENANCE: all values 0..3272 (reading it big-endian would give noise up to 65535).
        let r = ch.reader();
        let max = (0..fc.dims.voxel_count() as usize).map(|i| r.read(i)).fold(0.0f32, f32::max);
        assert_eq!(max, 3272.0);
    }

    #[test]
    fn engine_gzip_detached_u8() {
        let Some(dir) = data_dir() else { return };
        let fc = open(&dir.join("engine_256x256x128_uint8.nhdr")).unwrap();
        assert_eq!(fc.dims.as_array(), [256, 256, 128]);
        assert_eq!(fc.ty, VoxelType::U8);
        let (path, offset, enc, stored, _) = file_source(&fc);
        assert_eq!((offset, enc, stored), (0, Encoding::Gzip, StoredType::U8));
        let ch = fc.source.load(fc.dims).unwrap();
        assert!(!ch.is_mapped());
        // Decompress independently with the single-member decoder and compare everything.
        let mut expected = Vec::new();
        flate2::read::GzDecoder::new(File::open(path).unwrap()).read_to_end(&mut expected).unwrap();
        assert_eq!(expected.len(), 8_388_608);
        let r = ch.reader();
        assert!(expected.iter().enumerate().all(|(i, &b)| r.read(i) == b as f32));
        assert!(expected.iter().any(|&b| b > 100));
    }

    #[test]
    fn headsq_int16_becomes_f32() {
        let Some(dir) = data_dir() else { return };
        let fc = open(&dir.join("headsq_64x64x93_int16_le.nhdr")).unwrap();
        assert_eq!(fc.dims.as_array(), [64, 64, 93]);
        assert_eq!(fc.ty, VoxelType::F32);
        assert_eq!(file_source(&fc).3, StoredType::I16);
        let ch = fc.source.load(fc.dims).unwrap();
        assert_eq!(ch.ty(), VoxelType::F32);
        let bytes = std::fs::read(dir.join("headsq_64x64x93_int16_le.raw")).unwrap();
        for idx in [0, 1000, 64 * 64 * 46 + 64 * 32 + 32, 200_000, 380_927] {
            let v = i16::from_le_bytes([bytes[2 * idx], bytes[2 * idx + 1]]);
            assert_eq!(ch.value(idx), v as f32, "index {idx}");
        }
        let r = ch.reader();
        let max = (0..fc.dims.voxel_count() as usize).map(|i| r.read(i)).fold(f32::MIN, f32::max);
        assert_eq!(max, 3926.0); // PROVENANCE: values 0..3926
    }

    #[test]
    fn tooth_attached_header() {
        let Some(dir) = data_dir() else { return };
        let path = dir.join("tooth_103x94x161_uint8.nrrd");
        let fc = open(&path).unwrap();
        assert_eq!(fc.dims.as_array(), [103, 94, 161]);
        assert_eq!(fc.ty, VoxelType::U8);
        let (p, offset, enc, _, _) = file_source(&fc);
        assert_eq!((p, offset, enc), (path.as_path(), 300, Encoding::Raw));
        let ch = fc.source.load(fc.dims).unwrap();
        assert!(ch.is_mapped());
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(&bytes[298..300], b"\n\n");
        for idx in [0, 5000, 103 * 94 * 80 + 103 * 47 + 51, 1_558_801] {
            assert_eq!(ch.value(idx), bytes[300 + idx] as f32, "index {idx}");
        }
    }

    #[test]
    fn beach_interleaved_rgb_is_a_3_by_100_by_100_volume() {
        let Some(dir) = data_dir() else { return };
        let fc = open(&dir.join("beach_rgb_100x100.nrrd")).unwrap();
        assert_eq!(fc.dims.as_array(), [3, 100, 100]);
        assert_eq!(file_source(&fc).1, 167);
    }

    #[test]
    fn mri_slice_2d_gzip_big_endian() {
        let Some(dir) = data_dir() else { return };
        let fc = open(&dir.join("mri_slice_s1045_256x256_uint16_be.nhdr")).unwrap();
        assert_eq!(fc.dims.as_array(), [256, 256, 1]);
        let ch = fc.source.load(fc.dims).unwrap();
        assert_eq!(ch.endian(), Endian::Big);
        let r = ch.reader();
        let max = (0..65536).map(|i| r.read(i)).fold(0.0f32, f32::max);
        assert_eq!(max, 215.0); // PROVENANCE: high byte always 0, values 0..215
    }

    #[test]
    fn every_shared_header_opens() {
        let Some(dir) = data_dir() else { return };
        let mut n = 0;
        for entry in std::fs::read_dir(&dir).unwrap() {
            let p = entry.unwrap().path();
            if matches!(p.extension().and_then(|e| e.to_str()), Some("nhdr" | "nrrd")) {
                open(&p).unwrap_or_else(|e| panic!("{e}"));
                n += 1;
            }
        }
        assert!(n >= 15, "{n} headers");
    }

    /// Writes a header (and optionally data) to a temp file.
    fn nrrd(header: &str, data: &[u8]) -> TempFile {
        let mut bytes = header.as_bytes().to_vec();
        bytes.extend_from_slice(data);
        TempFile::with("t.nrrd", &bytes)
    }

    fn format_error(f: &TempFile) -> String {
        match open(&f.0) {
            Err(e @ DatasetError::Format { .. }) => {
                let msg = e.to_string();
                assert!(msg.contains(&f.0.display().to_string()), "{msg}");
                msg
            }
            other => panic!("expected a format error, got {other:?}"),
        }
    }

    #[test]
    fn attached_gzip_with_comments_keys_and_crlf() {
        let data: Vec<u8> = (0..24u16).flat_map(|v| (v * 1000).to_be_bytes()).collect();
        let header = "NRRD0005\r\n# a comment\r\ncontent:=key: value\r\ntype: unsigned short\r\ndimension: 3\r\n\
                      sizes: 2 3 4\r\nspacings: 1 1 2\r\nendian: big\r\nencoding: gz\r\n\r\n";
        let f = nrrd(header, &gzip(&data));
        let fc = open(&f.0).unwrap();
        assert_eq!(fc.dims.as_array(), [2, 3, 4]);
        let (_, offset, enc, stored, endian) = file_source(&fc);
        assert_eq!((offset, enc, stored, endian), (header.len() as u64, Encoding::Gzip, StoredType::U16, Endian::Big));
        let ch = fc.source.load(fc.dims).unwrap();
        assert_eq!(ch.value(23), 23000.0);
        assert_eq!(ch.value(1), 1000.0);
    }

    #[test]
    fn detached_relative_data_file_with_line_and_byte_skip() {
        let data = TempFile::with("t.dat", b"junk line\nsecond\nXYZ\x01\x02\x03\x04\x05\x06");
        let name = data.0.file_name().unwrap().to_str().unwrap();
        let f = nrrd(
            &format!("NRRD0004\ntype: int8\ndimension: 1\nsizes: 6\nline skip: 2\nbyte skip: 3\ndatafile: {name}\nencoding: raw\n"),
            &[],
        );
        let fc = open(&f.0).unwrap();
        assert_eq!(fc.dims.as_array(), [6, 1, 1]);
        assert_eq!(fc.ty, VoxelType::F32);
        let (p, offset, ..) = file_source(&fc);
        assert_eq!((p, offset), (data.0.as_path(), 20));
        let ch = fc.source.load(fc.dims).unwrap();
        assert_eq!((0..6).map(|i| ch.value(i)).collect::<Vec<_>>(), [1., 2., 3., 4., 5., 6.]);
    }

    #[test]
    fn size_mismatch_names_both_sizes_and_the_fields() {
        let f = nrrd("NRRD0004\ntype: uint8\ndimension: 2\nsizes: 4 4\nencoding: raw\n\n", &[0u8; 15]);
        let e = open(&f.0).unwrap_err();
        assert!(matches!(e, DatasetError::SizeMismatch { expected: 16, actual: 15, .. }), "{e:?}");
        let msg = e.to_string();
        assert!(msg.contains("sizes") && msg.contains("15") && msg.contains("16"), "{msg}");
        let f = nrrd("NRRD0004\ntype: uint8\ndimension: 2\nsizes: 4 4\nencoding: gzip\n\n", &gzip(&[0u8; 17]));
        assert!(matches!(open(&f.0), Err(DatasetError::SizeMismatch { expected: 16, actual: 17, .. })));
    }

    #[test]
    fn refusals_name_the_file_and_the_field() {
        let base = |ty: &str, dim: &str, sizes: &str, enc: &str| {
            format!("NRRD0004\ntype: {ty}\ndimension: {dim}\nsizes: {sizes}\nendian: little\nencoding: {enc}\n\n")
        };
        let cases: Vec<(String, &[&str])> = vec![
            (base("complex", "1", "4", "raw"), &["`type`", "unknown type `complex`"]),
            (base("int64", "1", "4", "raw"), &["`type`", "64-bit"]),
            (base("unsigned long long int", "1", "4", "raw"), &["`type`", "64-bit"]),
            (base("uint8", "1", "4", "ascii"), &["`encoding`", "not supported"]),
            (base("uint8", "1", "4", "lz4"), &["`encoding`", "unknown encoding `lz4`"]),
            (base("uint8", "4", "1 2 2 1", "raw"), &["`dimension`", "4"]),
            (base("uint8", "2", "4", "raw"), &["`sizes`", "1 sizes"]),
            (base("uint8", "1", "4 x", "raw"), &["`sizes`"]),
            ("NRRD0004\ntype: uint8\ndimension: 1\nencoding: raw\n\n".into(), &["missing required field `sizes`"]),
            ("NRRD0004\ntype: uint16\ndimension: 1\nsizes: 2\nencoding: raw\n\n".into(), &["`endian`"]),
            ("NRRD0004\ntype: uint8\ntype: uint8\n\n".into(), &["`type` is given twice"]),
            (
                "NRRD0004\ntype: uint8\ndimension: 1\nsizes: 4\nencoding: raw\nbyte skip: -1\n\n".into(),
                &["`byte skip`"],
            ),
            (
                "NRRD0004\ntype: uint8\ndimension: 1\nsizes: 4\nencoding: raw\ndata file: LIST\na.raw\nb.raw\n".into(),
                &["`data file`", "LIST"],
            ),
            (
                "NRRD0004\ntype: uint8\ndimension: 1\nsizes: 4\nencoding: raw\ndata file: s%03d.raw 1 10 1\n".into(),
                &["`data file`", "pattern"],
            ),
            ("NRRD0004\ntype: uint8\ndimension: 1\nsizes: 4\nencoding: raw".into(), &["no `data file`"]),
            ("NRRD0009\n".into(), &["NRRD0009"]),
            ("P5 this is a PGM\n".into(), &["not a NRRD file"]),
        ];
        for (header, needles) in cases {
            let data: &[u8] = if header.contains("\n\n") { &[0u8; 4] } else { &[] };
            let f = nrrd(&header, data);
            let msg = format_error(&f);
            for n in needles {
                assert!(msg.contains(n), "`{msg}` lacks `{n}` for header {header:?}");
            }
        }
    }

    #[test]
    fn sizes_that_dims_refuse_name_the_field_and_the_rule() {
        let f = nrrd("NRRD0004\ntype: uint8\ndimension: 2\nsizes: 4 0\nencoding: raw\n\n", &[]);
        let e = open(&f.0).unwrap_err();
        match &e {
            DatasetError::Dims {
                path,
                field: "field `sizes`",
                source: crate::dataset::DimsError::ZeroAxis { dims },
            } => {
                assert_eq!((path, *dims), (&f.0, [4, 0, 1]));
            }
            e => panic!("unexpected {e:?}"),
        }
        assert_eq!(
            crate::error::with_causes(&e),
            format!("{}: field `sizes`: dims [4, 0, 1]: every axis must be at least 1", f.0.display())
        );
    }

    #[test]
    fn every_type_spelling() {
        for (names, ty) in [
            ("uchar|unsigned char|uint8|uint8_t|UCHAR", StoredType::U8),
            ("signed char|int8|int8_t", StoredType::I8),
            ("short|short int|signed short|signed short int|int16|int16_t", StoredType::I16),
            ("ushort|unsigned short|unsigned short int|uint16|uint16_t|unsigned  short", StoredType::U16),
            ("int|signed int|int32|int32_t", StoredType::I32),
            ("uint|unsigned int|uint32|uint32_t", StoredType::U32),
            ("float", StoredType::F32),
            ("double", StoredType::F64),
        ] {
            for n in names.split('|') {
                assert_eq!(parse_type(n), Ok(ty), "{n}");
            }
        }
    }

    #[test]
    fn missing_data_file_is_an_io_error() {
        let f = nrrd("NRRD0004\ntype: uint8\ndimension: 1\nsizes: 4\nencoding: raw\ndata file: nowhere.raw\n", &[]);
        assert!(matches!(open(&f.0), Err(DatasetError::Io { .. })));
    }
}
