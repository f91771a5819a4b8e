//! What a command reads and writes, checked before any work and written together at the
//! end: an output aimed at an input (the same path, a link to it, the same inode) or at
//! another output is refused, every destination's directory must accept a new file, and
//! the outputs are staged as temporary files and renamed into place only once everything
//! has succeeded, so a failed run changes no file ([`crate::data::stage_write`]).

use std::fs;
use std::path::{Path, PathBuf};

use super::CliError;
use crate::data::{check_destination, commit_all, same_file, stage_write, DataError, StagedWrite};
use crate::model::ModelFile;

/// A file argument: the flag it came with (for messages) and the path.
pub(super) type Arg<'a> = (&'a str, &'a Path);

/// Refuse, before any work, an output that is one of the inputs or another output, and an
/// output that cannot be written (missing or read-only directory, a directory).
pub(super) fn check_paths(inputs: &[Arg<'_>], outputs: &[Arg<'_>]) -> Result<(), CliError> {
    refuse_inputs(inputs, outputs)?;
    for &(_, o) in outputs {
        check_destination(o)?;
    }
    Ok(())
}

/// Refuse an output that is one of the inputs or another output (see [`check_paths`]).
pub(super) fn refuse_inputs(inputs: &[Arg<'_>], outputs: &[Arg<'_>]) -> Result<(), CliError> {
    for (i, &(oflag, o)) in outputs.iter().enumerate() {
        for &(iflag, inp) in inputs {
            if same_file(o, inp) {
                return Err(CliError::Invalid(format!(
                    "{oflag} {} is the same file as {iflag} {}: refusing to overwrite an input \
                     (choose another output path)",
                    o.display(),
                    inp.display()
                )));
            }
        }
        for &(flag2, o2) in &outputs[..i] {
            if same_file(o, o2) {
                return Err(CliError::Invalid(format!(
                    "{flag2} {} and {oflag} {} are the same file: give each output its own path",
                    o2.display(),
                    o.display()
                )));
            }
        }
    }
    Ok(())
}

/// Check, before any work, that figures can be written into directory `dir` (it exists and
/// takes new files, or it can be created in an existing writable directory), and that it is
/// not an input.
pub(super) fn check_dir(flag: &str, dir: &Path, inputs: &[Arg<'_>]) -> Result<(), CliError> {
    for &(iflag, inp) in inputs {
        if same_file(dir, inp) {
            return Err(CliError::Invalid(format!(
                "{flag} {} is the same file as {iflag} {}",
                dir.display(),
                inp.display()
            )));
        }
    }
    let shown = dir.display().to_string();
    match fs::metadata(dir) {
        Ok(m) if m.is_dir() => check_destination(&dir.join(".lpvid-probe"))
            .map_err(|e| DataError::new(&shown, None, None, e.message).into()),
        Ok(_) => Err(DataError::new(&shown, None, None, "exists and is not a directory").into()),
        Err(_) => {
            // created at the end, in the nearest existing ancestor
            let mut anc = dir.parent();
            while let Some(a) = anc {
                if a.as_os_str().is_empty() || fs::metadata(a).is_ok() {
                    break;
                }
                anc = a.parent();
            }
            let base = match anc {
                Some(a) if !a.as_os_str().is_empty() => a.to_path_buf(),
                _ => PathBuf::from("."),
            };
            check_destination(&base.join(".lpvid-probe"))
                .map_err(|e| DataError::new(&shown, None, None, e.message).into())
        }
    }
}

/// The outputs of a command, staged and committed together.
#[derive(Debug, Default)]
pub(super) struct Outputs {
    staged: Vec<StagedWrite>,
}

impl Outputs {
    /// Stage a model file (validated as [`ModelFile::write`] does).
    pub(super) fn model(&mut self, m: &ModelFile, path: &Path) -> Result<(), CliError> {
        self.staged.push(m.stage(path)?);
        Ok(())
    }

    /// Stage bytes.
    pub(super) fn bytes(&mut self, path: &Path, bytes: &[u8]) -> Result<(), CliError> {
        self.staged.push(stage_write(path, bytes)?);
        Ok(())
    }

    /// Add a write already staged (a file written in pieces, [`crate::data::stage_writer`]).
    pub(super) fn staged(&mut self, s: StagedWrite) {
        self.staged.push(s);
    }

    /// Stage figures into `dir` (created now if needed).
    pub(super) fn figures(
        &mut self,
        dir: &Path,
        figs: &[(PathBuf, String)],
    ) -> Result<(), CliError> {
        fs::create_dir_all(dir).map_err(|e| {
            DataError::new(
                dir.display().to_string(),
                None,
                None,
                format!("cannot create: {e}"),
            )
        })?;
        for (p, text) in figs {
            self.bytes(p, text.as_bytes())?;
        }
        Ok(())
    }

    /// Put every staged output in place.
    pub(super) fn commit(self) -> Result<(), CliError> {
        commit_all(self.staged)?;
        Ok(())
    }
}
