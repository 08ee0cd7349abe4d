//! Output folders that f3g owns file by file, and temporary files that do not outlive a run.
//!
//! Rules (README, "What a command writes"):
//! - A command that writes into a folder records the files it wrote in the folder's manifest
//!   ([`MANIFEST`]); the next run of the same command removes those of them it does not write
//!   again (the frames of a longer animation) and nothing else.
//! - A folder that is not empty and holds no manifest of that command is refused unless the
//!   caller passes `overwrite` (the user's `--overwrite`): then files of the same names are
//!   replaced and nothing is removed.
//! - Nothing is written or removed through a symbolic link inside the folder (the folder itself
//!   may be one: the user named it).
//! - [`crate::write_atomic`]'s temporary files are listed while they exist, so an interrupt
//!   handler can remove them ([`remove_pending_temporaries`]); those a killed process left
//!   behind are removed by the next atomic write into the same folder.

use std::collections::{BTreeSet, HashSet};
use std::path::{Component, Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, SystemTime};

use crate::{IoError, TEMPORARY_PREFIX, write_atomic};

/// The manifest's file name: a header line `f3g-outputs 1 <command>`, then one written file a
/// line, relative to the folder, `/`-separated.
pub const MANIFEST: &str = ".f3g-outputs";

const HEADER: &str = "f3g-outputs 1";

/// A folder a command writes into, owning only the files it lists in its manifest.
#[derive(Debug)]
pub struct OutputDir {
    root: PathBuf,
    command: String,
    previous: BTreeSet<String>,
    written: BTreeSet<String>,
}

impl OutputDir {
    /// Opens `root` for `command`'s outputs; a missing folder is created with the first file
    /// (a command that fails before writing leaves nothing).
    ///
    /// A folder that holds other files and no manifest of `command` is refused unless
    /// `overwrite`.
    pub fn open(root: &Path, command: &str, overwrite: bool) -> Result<Self, IoError> {
        let manifest = root.join(MANIFEST);
        let previous = match std::fs::read_to_string(&manifest) {
            Ok(text) => match parse_manifest(&text) {
                Some((owner, files)) if owner == command => Some(files),
                Some((owner, _)) if !overwrite => {
                    return Err(IoError::new(
                        root,
                        format!(
                            "holds the outputs of `f3g {owner}`, not of `f3g {command}`: choose \
                             another folder, or pass --overwrite to write into it anyway (files of \
                             the same names are replaced, nothing is removed)"
                        ),
                    ));
                }
                Some(_) => None,
                None => return Err(IoError::new(&manifest, "not an f3g output manifest")),
            },
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => return Err(IoError::new(&manifest, e)),
        };
        if previous.is_none() && !overwrite && root.exists() {
            let mut entries = std::fs::read_dir(root).map_err(|e| IoError::new(root, e))?;
            if let Some(entry) = entries.next() {
                let entry = entry.map_err(|e| IoError::new(root, e))?;
                return Err(IoError::new(
                    root,
                    format!(
                        "is not empty (it holds {:?}) and has no record of files written by \
                         `f3g {command}`: choose a new or empty folder, or pass --overwrite to \
                         write into it anyway (files of the same names are replaced, nothing \
                         else is removed)",
                        entry.file_name()
                    ),
                ));
            }
        }
        Ok(Self {
            root: root.to_path_buf(),
            command: command.to_string(),
            previous: previous.unwrap_or_default(),
            written: BTreeSet::new(),
        })
    }

    /// The path to write `relative` (`/`-separated, inside the folder) at; its folders are
    /// created, and none of them may be a symbolic link or a file.
    pub fn file(&mut self, relative: &str) -> Result<PathBuf, IoError> {
        std::fs::create_dir_all(&self.root).map_err(|e| IoError::new(&self.root, e))?;
        let parts = components(relative).ok_or_else(|| {
            IoError::new(&self.root.join(relative), "not a path inside the folder")
        })?;
        let mut dir = self.root.clone();
        for part in &parts[..parts.len() - 1] {
            dir.push(part);
            match std::fs::symlink_metadata(&dir) {
                Ok(m) if m.file_type().is_symlink() => return Err(symlink_refused(&dir)),
                Ok(m) if m.is_dir() => {}
                Ok(_) => return Err(IoError::new(&dir, "is a file where a folder was expected")),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                    std::fs::create_dir(&dir).map_err(|e| IoError::new(&dir, e))?
                }
                Err(e) => return Err(IoError::new(&dir, e)),
            }
        }
        self.written.insert(parts.join("/"));
        Ok(dir.join(parts[parts.len() - 1]))
    }

    /// Removes the files of the previous run that this one did not write again (and folders
    /// left empty by that), then records this run's files. Returns how many files went.
    pub fn finish(self) -> Result<usize, IoError> {
        let mut removed = 0;
        for stale in self.previous.difference(&self.written) {
            if let Some(path) = self.inside(stale)? {
                std::fs::remove_file(&path).map_err(|e| IoError::new(&path, e))?;
                removed += 1;
                // Folders the run emptied (a `ply/` no longer asked for); a non-empty one stays.
                let mut dir = path.parent();
                while let Some(d) = dir.filter(|d| *d != self.root) {
                    if std::fs::remove_dir(d).is_err() {
                        break;
                    }
                    dir = d.parent();
                }
            }
        }
        std::fs::create_dir_all(&self.root).map_err(|e| IoError::new(&self.root, e))?;
        let mut text = format!("{HEADER} {}\n", self.command);
        for name in &self.written {
            text.push_str(name);
            text.push('\n');
        }
        write_atomic(&self.root.join(MANIFEST), text.as_bytes())?;
        Ok(removed)
    }

    /// The path of a listed file when it exists as a file (or link) reached without passing
    /// through a symbolic link; `None` when it is gone.
    fn inside(&self, relative: &str) -> Result<Option<PathBuf>, IoError> {
        let Some(parts) = components(relative) else {
            return Ok(None);
        };
        let mut path = self.root.clone();
        for (i, part) in parts.iter().enumerate() {
            path.push(part);
            match std::fs::symlink_metadata(&path) {
                Ok(m) if i + 1 < parts.len() && !m.is_dir() => return Ok(None),
                Ok(m) if i + 1 == parts.len() && m.is_dir() => return Ok(None),
                Ok(_) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
                Err(e) => return Err(IoError::new(&path, e)),
            }
        }
        Ok(Some(path))
    }
}

fn symlink_refused(path: &Path) -> IoError {
    IoError::new(
        path,
        "is a symbolic link: f3g writes only inside the output folder; remove the link or \
         choose another folder",
    )
}

/// The normal components of a relative `/`-separated path; `None` for an absolute path, `..`,
/// `.` or an empty one.
fn components(relative: &str) -> Option<Vec<&str>> {
    let parts: Vec<&str> = relative.split('/').collect();
    let normal = parts.iter().all(|p| {
        let mut c = Path::new(p).components();
        matches!((c.next(), c.next()), (Some(Component::Normal(_)), None)) && !p.contains('\\')
    });
    normal.then_some(parts)
}

fn parse_manifest(text: &str) -> Option<(&str, BTreeSet<String>)> {
    let mut lines = text.lines();
    let owner = lines.next()?.strip_prefix(HEADER)?.strip_prefix(' ')?;
    Some((
        owner,
        lines
            .filter(|l| components(l).is_some())
            .map(str::to_string)
            .collect(),
    ))
}

/// The temporary files [`write_atomic`] is writing now.
static PENDING: Mutex<BTreeSet<PathBuf>> = Mutex::new(BTreeSet::new());

/// Folders whose stale temporaries this process has already swept.
static SWEPT: Mutex<Option<HashSet<PathBuf>>> = Mutex::new(None);

/// A temporary file's name: the prefix, the writing process's id, a dash, then random letters;
/// the id tells a later process whether the writer is gone.
pub(crate) fn temporary_prefix() -> String {
    format!("{TEMPORARY_PREFIX}{}-", std::process::id())
}

/// Creates a temporary file in `dir` with `builder` and lists it, under the list's lock, so that
/// [`remove_pending_temporaries`] sees every temporary that exists.
pub(crate) fn create_pending(
    builder: &tempfile::Builder,
    dir: &Path,
) -> std::io::Result<tempfile::NamedTempFile> {
    let mut pending = PENDING.lock().unwrap_or_else(|e| e.into_inner());
    let file = builder.tempfile_in(dir)?;
    pending.insert(file.path().to_path_buf());
    Ok(file)
}

pub(crate) fn unregister_pending(path: &Path) {
    PENDING
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .remove(path);
}

/// Removes the temporary files of atomic writes in progress and keeps any new one from being
/// created (a writer that tries waits for ever): for an interrupt handler, just before the
/// process exits. Returns how many were removed.
pub fn remove_pending_temporaries() -> usize {
    let mut pending = PENDING.lock().unwrap_or_else(|e| e.into_inner());
    let removed = remove_all(&std::mem::take(&mut *pending));
    // Held until the process ends: the other threads go on writing until then.
    std::mem::forget(pending);
    removed
}

fn remove_all(paths: &BTreeSet<PathBuf>) -> usize {
    paths
        .iter()
        .filter(|p| std::fs::remove_file(p).is_ok())
        .count()
}

/// How old a temporary file without a readable writer id (or on a system without `/proc`) must
/// be to count as left behind.
const STALE_AGE: Duration = Duration::from_secs(24 * 3600);

/// Removes, once per folder and process, the temporary files in `dir` that a process which no
/// longer runs left behind; returns how many went. Errors are ignored: a temporary that cannot
/// be removed is no reason to fail the write.
pub(crate) fn sweep_stale_temporaries(dir: &Path) -> usize {
    {
        let mut swept = SWEPT.lock().unwrap_or_else(|e| e.into_inner());
        if !swept
            .get_or_insert_with(HashSet::new)
            .insert(dir.to_path_buf())
        {
            return 0;
        }
    }
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    let proc_fs = Path::new("/proc/self").exists();
    let mut removed = 0;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(rest) = name.to_str().and_then(|n| n.strip_prefix(TEMPORARY_PREFIX)) else {
            continue;
        };
        let writer: Option<u32> = rest.split_once('-').and_then(|(id, _)| id.parse().ok());
        let stale = match writer {
            Some(id) if id == std::process::id() => false,
            Some(id) if proc_fs => !Path::new("/proc").join(id.to_string()).exists(),
            _ => entry
                .metadata()
                .and_then(|m| m.modified())
                .ok()
                .and_then(|t| SystemTime::now().duration_since(t).ok())
                .is_some_and(|age| age > STALE_AGE),
        };
        let is_file = entry.file_type().is_ok_and(|t| t.is_file());
        if stale && is_file && std::fs::remove_file(entry.path()).is_ok() {
            removed += 1;
        }
    }
    removed
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &mut OutputDir, name: &str) {
        let path = dir.file(name).unwrap();
        write_atomic(&path, name.as_bytes()).unwrap();
    }

    fn names(root: &Path) -> Vec<String> {
        let mut all = Vec::new();
        let mut stack = vec![root.to_path_buf()];
        while let Some(d) = stack.pop() {
            for e in std::fs::read_dir(&d).unwrap().flatten() {
                let p = e.path();
                if e.file_type().unwrap().is_dir() {
                    stack.push(p.clone());
                }
                all.push(
                    p.strip_prefix(root)
                        .unwrap()
                        .to_string_lossy()
                        .replace('\\', "/"),
                );
            }
        }
        all.sort();
        all
    }

    #[test]
    fn a_second_run_removes_only_its_own_files_it_did_not_write_again() {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().join("out");
        // Opening creates nothing: a command that fails before its first file leaves nothing.
        drop(OutputDir::open(&root, "animate", false).unwrap());
        assert!(!root.exists());
        let mut out = OutputDir::open(&root, "animate", false).unwrap();
        for name in [
            "frames/frame_00000.png",
            "frames/frame_00001.png",
            "ply/frame_00000.ply",
        ] {
            write(&mut out, name);
        }
        out.finish().unwrap();
        // The user's files beside them, named like the command's.
        for name in [
            "frames/frame_abc.txt",
            "frames/frame_00001.png.bak",
            "frames/frame_1.png",
        ] {
            std::fs::write(root.join(name), b"mine").unwrap();
        }
        let mut out = OutputDir::open(&root, "animate", false).unwrap();
        write(&mut out, "frames/frame_00000.png");
        assert_eq!(out.finish().unwrap(), 2);
        assert_eq!(
            names(&root),
            [
                MANIFEST,
                "frames",
                "frames/frame_00000.png",
                "frames/frame_00001.png.bak",
                "frames/frame_1.png",
                "frames/frame_abc.txt"
            ]
        );
    }

    #[test]
    fn a_folder_of_someone_else_needs_overwrite_and_then_loses_nothing() {
        let tmp = tempfile::tempdir().unwrap();
        std::fs::write(tmp.path().join("index.html"), b"mine").unwrap();
        std::fs::write(tmp.path().join("notes.txt"), b"mine").unwrap();
        let err = OutputDir::open(tmp.path(), "view", false).unwrap_err();
        assert!(err.to_string().contains("--overwrite"), "{err}");
        assert!(err.to_string().contains("is not empty"), "{err}");
        let mut out = OutputDir::open(tmp.path(), "view", true).unwrap();
        write(&mut out, "index.html");
        out.finish().unwrap();
        assert_eq!(
            std::fs::read(tmp.path().join("notes.txt")).unwrap(),
            b"mine"
        );
        assert_eq!(
            std::fs::read(tmp.path().join("index.html")).unwrap(),
            b"index.html"
        );
        // Another command's folder is refused too.
        let err = OutputDir::open(tmp.path(), "animate", false).unwrap_err();
        assert!(err.to_string().contains("`f3g view`"), "{err}");
    }

    #[cfg(unix)]
    #[test]
    fn nothing_is_written_or_removed_through_a_link() {
        let tmp = tempfile::tempdir().unwrap();
        let elsewhere = tmp.path().join("elsewhere");
        std::fs::create_dir(&elsewhere).unwrap();
        std::fs::write(elsewhere.join("frame_00000.png"), b"precious").unwrap();
        let root = tmp.path().join("out");
        let mut out = OutputDir::open(&root, "animate", false).unwrap();
        write(&mut out, "frames/frame_00000.png");
        out.finish().unwrap();
        // The user replaces the frames folder by a link to their own.
        std::fs::remove_dir_all(root.join("frames")).unwrap();
        std::os::unix::fs::symlink(&elsewhere, root.join("frames")).unwrap();
        let mut out = OutputDir::open(&root, "animate", false).unwrap();
        let err = out.file("frames/frame_00000.png").unwrap_err();
        assert!(err.to_string().contains("symbolic link"), "{err}");
        // Finishing without writing it would remove the listed frame: not through the link.
        assert_eq!(out.finish().unwrap(), 0);
        assert_eq!(
            std::fs::read(elsewhere.join("frame_00000.png")).unwrap(),
            b"precious"
        );
    }

    #[test]
    fn paths_outside_the_folder_are_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let mut out = OutputDir::open(tmp.path(), "animate", false).unwrap();
        for bad in ["../x", "/etc/passwd", "a/../../x", "", "a//b", "./a"] {
            assert!(out.file(bad).is_err(), "{bad}");
        }
        // A manifest naming such paths is read without them.
        let (_, files) =
            parse_manifest("f3g-outputs 1 animate\n../x\n/etc/passwd\nok.png\n").unwrap();
        assert_eq!(files.into_iter().collect::<Vec<_>>(), ["ok.png"]);
    }

    #[test]
    fn temporaries_of_a_killed_writer_go_with_the_next_write() {
        let tmp = tempfile::tempdir().unwrap();
        // No process has this id (above Linux's pid_max limit of 2^22).
        let dead = tmp
            .path()
            .join(format!("{TEMPORARY_PREFIX}4294967295-abcdef"));
        let ours = tmp.path().join(format!("{}live", temporary_prefix()));
        std::fs::write(&dead, b"half a file").unwrap();
        std::fs::write(&ours, b"being written").unwrap();
        write_atomic(&tmp.path().join("new.png"), b"x").unwrap();
        if Path::new("/proc/self").exists() {
            assert!(!dead.exists());
        }
        assert!(ours.exists());
    }

    /// The list an interrupt handler empties (the global one is not emptied here: other tests
    /// write beside this one).
    #[test]
    fn pending_temporaries_are_listed_while_written() {
        let tmp = tempfile::tempdir().unwrap();
        let prefix = temporary_prefix();
        let mut builder = tempfile::Builder::new();
        builder.prefix(&prefix);
        let file = create_pending(&builder, tmp.path()).unwrap();
        let path = file.path().to_path_buf();
        assert!(PENDING.lock().unwrap().contains(&path));
        assert_eq!(remove_all(&BTreeSet::from([path.clone()])), 1);
        assert!(!path.exists());
        unregister_pending(&path);
        assert!(!PENDING.lock().unwrap().contains(&path));
    }
}
