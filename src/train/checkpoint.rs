//! Checkpoints of a training stage: the whole trainer, postcard-encoded, with a
//! format version and the stage's name, written atomically (temp file + rename).

use std::path::Path;

use serde::{de::DeserializeOwned, Deserialize, Serialize};

use crate::error::{write_atomic, Error, Result};

/// Version tag of the checkpoint layout (bump when a trainer's fields change).
const FORMAT: u32 = 5;

#[derive(Serialize, Deserialize)]
struct Checkpoint<T> {
    format: u32,
    stage: String,
    trainer: T,
    /// Wall time spent before this checkpoint (seconds), so metrics add up over resumes.
    elapsed_s: f64,
}

/// Write `trainer` of stage `stage` to `path` atomically.
pub fn save<T: Serialize>(path: &Path, stage: &str, trainer: &T, elapsed_s: f64) -> Result<()> {
    #[derive(Serialize)]
    struct Borrowed<'a, T> {
        format: u32,
        stage: &'a str,
        trainer: &'a T,
        elapsed_s: f64,
    }
    let bytes = postcard::to_stdvec(&Borrowed { format: FORMAT, stage, trainer, elapsed_s })
        .map_err(|e| Error::Other(format!("encoding checkpoint: {e}")))?;
    write_atomic(path, &bytes)
}

/// Read a checkpoint of stage `stage` written by [`save`]; `check` validates the
/// trainer's internal consistency (its message names what is wrong).
pub fn load<T: DeserializeOwned>(
    path: &Path,
    stage: &str,
    check: impl FnOnce(&T) -> std::result::Result<(), String>,
) -> Result<(T, f64)> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    // The header first, so a checkpoint of another stage or version gets a clear message.
    #[derive(Deserialize)]
    struct Header {
        format: u32,
        stage: String,
    }
    let (header, _): (Header, _) =
        postcard::take_from_bytes(&bytes).map_err(|e| Error::bad_file(path, format!("not an aim checkpoint: {e}")))?;
    if header.format != FORMAT {
        return Err(Error::bad_file(path, format!("checkpoint format {} (this build reads {FORMAT})", header.format)));
    }
    if header.stage != stage {
        return Err(Error::bad_file(path, format!("a {} checkpoint, not {stage}", header.stage)));
    }
    let ck: Checkpoint<T> =
        postcard::from_bytes(&bytes).map_err(|e| Error::bad_file(path, format!("not a {stage} checkpoint: {e}")))?;
    check(&ck.trainer).map_err(|m| Error::bad_file(path, m))?;
    Ok((ck.trainer, ck.elapsed_s))
}
