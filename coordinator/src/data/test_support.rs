//! What the data tests share: manifest entries for given bytes, and zip archives.

use std::io::{Cursor, Write};

use sha2::{Digest, Sha256};
use zip::write::SimpleFileOptions;
use zip::{CompressionMethod, ZipWriter};

use super::verify::hex;

/// A zip archive of `members` (name, bytes, deflated?), as a wheel is laid out.
pub(super) fn zip(members: &[(&str, &[u8], bool)]) -> Vec<u8> {
    let mut archive = ZipWriter::new(Cursor::new(Vec::new()));
    for &(name, data, deflate) in members {
        let method = if deflate { CompressionMethod::Deflated } else { CompressionMethod::Stored };
        archive.start_file(name, SimpleFileOptions::default().compression_method(method)).unwrap();
        archive.write_all(data).unwrap();
    }
    // A comment, as some archivers write: the directory's end is then not the file's.
    archive.set_comment("comment").unwrap();
    archive.finish().unwrap().into_inner()
}

pub(super) fn sha(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

pub(super) fn entry(name: &str, bytes: &[u8]) -> String {
    format!(
        "[[file]]\nname = \"{name}\"\nbytes = {}\nsha256 = \"{}\"\nabout = \"x\"\nlicence = \"x\"\n",
        bytes.len(),
        sha(bytes)
    )
}
