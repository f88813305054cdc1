//! Numbered frame sequences: file name patterns (`dir/frame_{}.vtk`, `out_{:04}.ply`), frame
//! ranges (`0..20`, `0..=20`, `0..100:5`), the checks of a run's outputs before any work, and
//! [`Sequence`], the runner that takes the frames in parallel runs of consecutive frames.

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use rayon::prelude::*;

use crate::{Error, io};

/// Errors of patterns and ranges.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SequenceError {
    /// The pattern's braces are not `{}` or `{:0N}`, or there are several.
    #[error(
        "bad frame pattern `{pattern}`: {reason} (use one `{{}}` or `{{:04}}` for the frame number)"
    )]
    BadPattern {
        pattern: String,
        reason: &'static str,
    },
    /// The range is not `A..B`, `A..=B`, optionally followed by `:STEP`.
    #[error("bad frame range `{range}`: expected A..B, A..=B, A..B:STEP or A..=B:STEP")]
    BadRange { range: String },
    /// The range holds no frame.
    #[error("frame range `{range}` holds no frame")]
    EmptyRange { range: String },
    /// No file of the sequence was found on disk.
    #[error("no file matches `{pattern}` in {}", dir.display())]
    NoFrames { pattern: String, dir: PathBuf },
    /// Frames of the range asked for have no file.
    #[error(
        "frames of `{range}` have no file: {}{} (`{}` does not exist); give a --frames range of frames that exist",
        list(missing), if *more { " and more" } else { "" }, first_path.display()
    )]
    MissingFrames {
        range: String,
        /// The first few missing frames.
        missing: Vec<usize>,
        /// Whether there are more than those.
        more: bool,
        first_path: PathBuf,
    },
    /// `--shard` is not `K/N` with 1 <= K <= N, or `slurm` with usable array variables.
    #[error("bad shard `{shard}`: {reason}")]
    BadShard { shard: String, reason: String },
}

fn list(frames: &[usize]) -> String {
    frames
        .iter()
        .map(usize::to_string)
        .collect::<Vec<_>>()
        .join(", ")
}

/// A file name with one placeholder for the frame number.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FramePattern {
    prefix: String,
    suffix: String,
    /// zero-padded width, from `{:0N}`
    width: Option<usize>,
}

impl FramePattern {
    /// Parses a pattern; `Ok(None)` when the text has no placeholder (a single file).
    pub fn parse(text: &str) -> Result<Option<Self>, SequenceError> {
        let bad = |reason| SequenceError::BadPattern {
            pattern: text.to_owned(),
            reason,
        };
        let Some(open) = text.find('{') else {
            return if text.contains('}') {
                Err(bad("a `}` without `{`"))
            } else {
                Ok(None)
            };
        };
        let close = text[open..]
            .find('}')
            .map(|k| open + k)
            .ok_or_else(|| bad("a `{` without `}`"))?;
        let inner = &text[open + 1..close];
        let width = match inner {
            "" => None,
            spec => {
                let digits = spec
                    .strip_prefix(":0")
                    .or_else(|| spec.strip_prefix(':'))
                    .ok_or_else(|| bad("unknown format inside the braces"))?;
                Some(
                    digits
                        .parse::<usize>()
                        .map_err(|_| bad("the width is not a number"))?
                        .min(20),
                )
            }
        };
        let suffix = &text[close + 1..];
        if suffix.contains('{') || suffix.contains('}') {
            return Err(bad("more than one placeholder"));
        }
        Ok(Some(Self {
            prefix: text[..open].to_owned(),
            suffix: suffix.to_owned(),
            width,
        }))
    }

    /// The pattern's path without its number and the separator before it (`_`, `-`, `.` or a
    /// space): `out/mesh_{:04}.usda` -> `out/mesh.usda`, the name of a file that stands for
    /// the whole sequence; `sequence` when nothing of the name is left (`out/{}.usda` ->
    /// `out/sequence.usda`).
    #[must_use]
    pub fn without_number(&self) -> PathBuf {
        let prefix = self.prefix.trim_end_matches(['_', '-', '.', ' ']);
        let name_starts = prefix.rfind(['/', '\\']).map_or(0, |i| i + 1);
        if prefix.len() == name_starts {
            PathBuf::from(format!("{prefix}sequence{}", self.suffix))
        } else {
            PathBuf::from(format!("{prefix}{}", self.suffix))
        }
    }

    /// The file name of frame `frame`.
    #[must_use]
    pub fn path(&self, frame: usize) -> PathBuf {
        let number = match self.width {
            Some(w) => format!("{frame:0w$}"),
            None => frame.to_string(),
        };
        PathBuf::from(format!("{}{number}{}", self.prefix, self.suffix))
    }

    /// The frames to work on: those of `range`, every one checked to have its file before any
    /// work starts (refused with the first few missing, [`SequenceError::MissingFrames`]), or
    /// with no range every file on disk that matches. Nothing is allocated per frame of the
    /// range beyond the files found, so a range of a billion frames costs what the files do.
    pub fn frames(&self, range: Option<FrameRange>) -> Result<Vec<usize>, SequenceError> {
        const SHOWN: usize = 5;
        let Some(range) = range else {
            return self.existing_frames();
        };
        let mut found = Vec::new();
        let mut missing = Vec::new();
        let mut more = false;
        for f in range.frames() {
            if self.path(f).is_file() {
                found.push(f);
            } else if missing.len() == SHOWN {
                more = true;
                break;
            } else {
                missing.push(f);
            }
        }
        if let Some(&first) = missing.first() {
            return Err(SequenceError::MissingFrames {
                range: range.to_string(),
                missing,
                more,
                first_path: self.path(first),
            });
        }
        Ok(found)
    }

    /// The frame numbers of the files on disk that match the pattern, sorted.
    pub fn existing_frames(&self) -> Result<Vec<usize>, SequenceError> {
        let full = format!("{}{{}}{}", self.prefix, self.suffix);
        let template = Path::new(&full);
        let dir = template
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."))
            .to_owned();
        let name_prefix = Path::new(&format!("{}x", self.prefix))
            .file_name()
            .map(|n| n.to_string_lossy().trim_end_matches('x').to_owned())
            .unwrap_or_default();
        let mut frames: Vec<usize> = std::fs::read_dir(&dir)
            .map(|entries| {
                entries
                    .flatten()
                    .filter_map(|e| {
                        let name = e.file_name().to_string_lossy().into_owned();
                        let digits = name
                            .strip_prefix(&name_prefix)?
                            .strip_suffix(&self.suffix)?;
                        if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
                            return None;
                        }
                        let frame: usize = digits.parse().ok()?;
                        (self.path(frame).file_name() == Some(e.file_name().as_os_str()))
                            .then_some(frame)
                    })
                    .collect()
            })
            .unwrap_or_default();
        frames.sort_unstable();
        if frames.is_empty() {
            return Err(SequenceError::NoFrames { pattern: full, dir });
        }
        Ok(frames)
    }
}

/// A range of frame numbers with a step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameRange {
    /// First frame.
    pub start: usize,
    /// One past the last frame.
    pub end: usize,
    /// Distance between frames (>= 1).
    pub step: usize,
}

impl FrameRange {
    /// The frame numbers in order.
    pub fn frames(&self) -> impl Iterator<Item = usize> + '_ {
        (self.start..self.end).step_by(self.step)
    }
}

impl std::fmt::Display for FrameRange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}..{}", self.start, self.end)?;
        if self.step != 1 {
            write!(f, ":{}", self.step)?;
        }
        Ok(())
    }
}

impl FromStr for FrameRange {
    type Err = SequenceError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = || SequenceError::BadRange {
            range: s.to_owned(),
        };
        let (span, step) = match s.split_once(':') {
            Some((span, step)) => (span, step.trim().parse::<usize>().map_err(|_| bad())?),
            None => (s, 1),
        };
        let (a, b) = span.split_once("..").ok_or_else(bad)?;
        let (b, inclusive) = match b.strip_prefix('=') {
            Some(b) => (b, true),
            None => (b, false),
        };
        let start: usize = a.trim().parse().map_err(|_| bad())?;
        let last: usize = b.trim().parse().map_err(|_| bad())?;
        let end = if inclusive {
            last.checked_add(1).ok_or_else(bad)?
        } else {
            last
        };
        if step == 0 {
            return Err(bad());
        }
        if end <= start {
            return Err(SequenceError::EmptyRange {
                range: s.to_owned(),
            });
        }
        Ok(Self { start, end, step })
    }
}

/// One of `count` contiguous chunks of a sequence's frames (issue 39): `--shard K/N`, the
/// `index`-th (1-based), or `--shard slurm` from a Slurm job array's variables. A farm or a
/// scheduler runs the chunks as tasks; each loads the sequence's plan and warms up on the
/// frames before its first (`pipeline::SequencePlan`, `Pipeline::warm_up`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    /// Which chunk, from 1.
    pub index: usize,
    /// How many chunks.
    pub count: usize,
}

impl Shard {
    /// The `index`-th of `count` chunks, checked (1 <= index <= count).
    pub fn new(index: usize, count: usize) -> Result<Self, SequenceError> {
        if count == 0 || index == 0 || index > count {
            return Err(SequenceError::BadShard {
                shard: format!("{index}/{count}"),
                reason: "K/N needs 1 <= K <= N (K counts from 1)".into(),
            });
        }
        Ok(Self { index, count })
    }

    /// The shard of a Slurm array task: `SLURM_ARRAY_TASK_ID` - `SLURM_ARRAY_TASK_MIN` + 1 of
    /// `SLURM_ARRAY_TASK_COUNT` (`var` reads a variable: `std::env::var(..).ok()`).
    pub fn from_slurm(var: impl Fn(&str) -> Option<String>) -> Result<Self, SequenceError> {
        let bad = |reason: String| SequenceError::BadShard {
            shard: "slurm".into(),
            reason,
        };
        let read = |name: &str| -> Result<usize, SequenceError> {
            let v = var(name).ok_or_else(|| {
                bad(format!(
                    "{name} is not set (run it as a Slurm array task: sbatch --array=1-N)"
                ))
            })?;
            v.trim()
                .parse()
                .map_err(|_| bad(format!("{name}={v} is not a whole number")))
        };
        let (id, min, count) = (
            read("SLURM_ARRAY_TASK_ID")?,
            read("SLURM_ARRAY_TASK_MIN")?,
            read("SLURM_ARRAY_TASK_COUNT")?,
        );
        if id < min || id - min >= count {
            return Err(bad(format!(
                "SLURM_ARRAY_TASK_ID={id} is not among the {count} tasks from SLURM_ARRAY_TASK_MIN={min} (an array with a step is not supported: use --array=A-B)"
            )));
        }
        Self::new(id - min + 1, count)
    }

    /// This chunk of `frames`: contiguous, the chunks' sizes differing by at most one (the
    /// first ones the larger); empty when there are fewer frames than chunks.
    #[must_use]
    pub fn of<'a>(&self, frames: &'a [usize]) -> &'a [usize] {
        let (n, k) = (frames.len(), self.count);
        let start = |i: usize| i * (n / k) + i.min(n % k);
        &frames[start(self.index - 1)..start(self.index)]
    }
}

impl FromStr for Shard {
    type Err = SequenceError;

    /// `K/N`, or `slurm` (the variables of the environment).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if s.trim() == "slurm" {
            return Self::from_slurm(|name| std::env::var(name).ok());
        }
        let bad = || SequenceError::BadShard {
            shard: s.to_owned(),
            reason: "expected K/N (the K-th of N chunks, from 1) or slurm".into(),
        };
        let (k, n) = s.split_once('/').ok_or_else(bad)?;
        let k = k.trim().parse().map_err(|_| bad())?;
        let n = n.trim().parse().map_err(|_| bad())?;
        Self::new(k, n).map_err(|e| match e {
            SequenceError::BadShard { reason, .. } => SequenceError::BadShard {
                shard: s.to_owned(),
                reason,
            },
            other => other,
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Outputs of a run and the sequence runner

/// Whether an output belongs to a sequence (where `--skip-existing` is the other way out).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OutputKind {
    /// One file of a one-file run.
    Single,
    /// A frame's file of a sequence.
    Frame,
}

/// Checks an output before any work: its folder exists and takes files, it is not the input,
/// and it does not exist unless `force` (`--force`) replaces it.
pub fn check_output(
    out: &Path,
    input: Option<&Path>,
    force: bool,
    kind: OutputKind,
) -> Result<(), Error> {
    check_replaceable(out, input, force, kind)?;
    check_folder(out)
}

/// [`check_output`] without the folder: for the frames of a sequence, whose folder is checked
/// once.
pub fn check_replaceable(
    out: &Path,
    input: Option<&Path>,
    force: bool,
    kind: OutputKind,
) -> Result<(), Error> {
    let refuse = |kind: std::io::ErrorKind, why: String| -> Result<(), Error> {
        Err(io::IoError::Os {
            path: out.to_owned(),
            source: std::io::Error::new(kind, why),
        }
        .into())
    };
    let same = input.is_some_and(|i| {
        i == out || matches!((std::fs::canonicalize(i), std::fs::canonicalize(out)), (Ok(a), Ok(b)) if a == b)
    });
    if same {
        return refuse(
            std::io::ErrorKind::AlreadyExists,
            "refusing to overwrite: it is the input file".into(),
        );
    }
    if out.is_dir() {
        return refuse(
            std::io::ErrorKind::AlreadyExists,
            "is a folder; name a file to write".into(),
        );
    }
    if out.exists() && !force {
        return refuse(
            std::io::ErrorKind::AlreadyExists,
            match kind {
                OutputKind::Single => {
                    "refusing to overwrite: it exists; pass --force to replace it"
                }
                OutputKind::Frame => {
                    "refusing to overwrite: this frame's output exists; pass --force to replace \
                     the frames that exist, or --skip-existing to keep them and do only the others"
                }
            }
            .into(),
        );
    }
    Ok(())
}

/// The folder `out` goes into exists and takes a new file (probed by creating and removing one).
pub fn check_folder(out: &Path) -> Result<(), Error> {
    let dir = match out.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let fail = |why: String| -> Result<(), Error> {
        Err(io::IoError::Os {
            path: out.to_owned(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, why),
        }
        .into())
    };
    if !dir.is_dir() {
        return fail(format!(
            "the output folder {} does not exist (create it first; nothing was done)",
            dir.display()
        ));
    }
    let probe = dir.join(format!(".fluid-surfels-probe-{}", std::process::id()));
    match std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
    {
        Ok(_) => {
            // a probe left behind is harmless; nothing to report if its removal fails
            let _ = std::fs::remove_file(&probe);
            Ok(())
        }
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(()),
        Err(e) => fail(format!(
            "cannot write into the output folder {} ({e}; nothing was done)",
            dir.display()
        )),
    }
}

/// How a command runs over the frames of a sequence: which frames, their outputs, how many at
/// once. Used by the command line's `detect`, `refine` and `surfels`, and open to library and
/// Python users.
pub struct Sequence<'a> {
    /// Input file pattern.
    pub input: &'a FramePattern,
    /// Frames asked for.
    pub frames: Vec<usize>,
    /// Output patterns (a frame is done when all exist).
    pub outputs: Vec<FramePattern>,
    /// Frames at once.
    pub jobs: usize,
    /// Skip frames whose outputs all exist.
    pub skip_existing: bool,
    /// Replace existing outputs.
    pub force: bool,
    /// What the frames are for, in progress reports (`"detect"`, `"refine"`...).
    pub label: &'static str,
    /// Called once with the number of frames to do, then after each frame done (from the
    /// worker threads); the command line draws its progress bar with it.
    pub progress: Option<Box<dyn Fn(Progress) + Sync + 'a>>,
    /// The chunk of `frames` this run does (`--shard K/N`); `None`: every frame.
    pub shard: Option<Shard>,
    /// How many frames of `frames` before each frame a job processes, back to the one it
    /// processed last, go through [`Sequence::run_warm`]'s warm-up alone (`--warmup`): a job's
    /// first frame, a shard's, a frame after skipped ones then carry the serial run's
    /// hysteresis. 0: none.
    pub warmup: usize,
}

/// What [`Sequence::progress`] is told.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Progress {
    /// The run starts with this many frames to do.
    Start(usize),
    /// One more frame is done.
    Frame,
    /// The run ended (done, or stopped by an error).
    End,
}

/// What [`Sequence::run`] reports.
#[derive(Debug)]
pub struct SequenceRun<R> {
    /// Per processed frame, in frame order.
    pub results: Vec<R>,
    /// Frames skipped because their outputs existed.
    pub skipped: Vec<usize>,
    /// Jobs actually used.
    pub jobs: usize,
    /// Wall-clock seconds of the processing.
    pub seconds: f64,
}

impl Sequence<'_> {
    /// Frames still to do and frames skipped, after `skip_existing` and the refusal to
    /// overwrite without `force` (checked for every frame before anything runs).
    pub fn plan(&self) -> Result<(Vec<usize>, Vec<usize>), Error> {
        let mut todo = Vec::new();
        let mut skipped = Vec::new();
        let mut folders = std::collections::HashSet::new();
        let chunk = self.shard.map_or(&self.frames[..], |s| s.of(&self.frames));
        for &f in chunk {
            let targets: Vec<PathBuf> = self.outputs.iter().map(|p| p.path(f)).collect();
            if self.skip_existing && !targets.is_empty() && targets.iter().all(|t| t.exists()) {
                skipped.push(f);
                continue;
            }
            let input = self.input.path(f);
            for t in &targets {
                check_replaceable(t, Some(&input), self.force, OutputKind::Frame)?;
                if folders.insert(t.parent().map(Path::to_path_buf)) {
                    check_folder(t)?;
                }
            }
            todo.push(f);
        }
        Ok((todo, skipped))
    }

    /// Runs `process(state, frame)` over the frames to do: `jobs` runs of consecutive frames in
    /// parallel, each with its own `state` (made by `make_state`) used in frame order. Stops at
    /// the first error.
    pub fn run<S, R: Send>(
        &self,
        make_state: impl Fn() -> Result<S, Error> + Sync,
        process: impl Fn(&mut S, usize) -> Result<R, Error> + Sync,
    ) -> Result<SequenceRun<R>, Error> {
        self.run_warm(make_state, |_, _| Ok(()), process)
    }

    /// [`Sequence::run`] with a warm-up: before each frame a job processes, `warm_up(state,
    /// frame)` on the [`Sequence::warmup`] frames of `frames` just before it that the job has
    /// not processed (those before a job's first frame, a shard's, or between skipped ones), so
    /// that the state carries what the serial run's would.
    pub fn run_warm<S, R: Send>(
        &self,
        make_state: impl Fn() -> Result<S, Error> + Sync,
        warm_up: impl Fn(&mut S, usize) -> Result<(), Error> + Sync,
        process: impl Fn(&mut S, usize) -> Result<R, Error> + Sync,
    ) -> Result<SequenceRun<R>, Error> {
        let (todo, skipped) = self.plan()?;
        let jobs = jobs(self.jobs, todo.len())?;
        let block = todo.len().div_ceil(jobs).max(1);
        let blocks: Vec<&[usize]> = todo.chunks(block).collect();
        let tell = |p: Progress| {
            if let Some(progress) = &self.progress {
                progress(p);
            }
        };
        tell(Progress::Start(todo.len()));
        let failed = AtomicBool::new(false);
        let first_error: Mutex<Option<Error>> = Mutex::new(None);
        let fail = |e: Error| {
            failed.store(true, Ordering::SeqCst);
            first_error
                .lock()
                .expect("no panic holds the lock")
                .get_or_insert(e);
        };
        let start = Instant::now();
        let run_block = |frames: &[usize]| -> Vec<(usize, R)> {
            let mut out = Vec::new();
            let mut state = match make_state() {
                Ok(s) => s,
                Err(e) => {
                    fail(e);
                    return out;
                }
            };
            let mut next = 0;
            for &f in frames {
                if failed.load(Ordering::SeqCst) {
                    break;
                }
                let at = self.index_of(f);
                let warm = &self.frames[next.max(at.saturating_sub(self.warmup))..at];
                if let Err(e) = warm.iter().try_for_each(|&w| warm_up(&mut state, w)) {
                    fail(e);
                    break;
                }
                next = at + 1;
                match process(&mut state, f) {
                    Ok(r) => out.push((f, r)),
                    Err(e) => {
                        fail(e);
                        break;
                    }
                }
                tell(Progress::Frame);
            }
            out
        };
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(jobs.max(rayon::current_num_threads()))
            .build()
            .map_err(|e| Error::InvalidArgument {
                argument: "jobs",
                reason: e.to_string(),
            })?;
        let mut done: Vec<(usize, R)> =
            pool.install(|| blocks.par_iter().flat_map_iter(|b| run_block(b)).collect());
        tell(Progress::End);
        if let Some(e) = first_error.into_inner().expect("no panic holds the lock") {
            return Err(e);
        }
        done.sort_by_key(|(f, _)| *f);
        Ok(SequenceRun {
            results: done.into_iter().map(|(_, r)| r).collect(),
            skipped,
            jobs,
            seconds: start.elapsed().as_secs_f64(),
        })
    }
}

impl Sequence<'_> {
    /// Where `frame` lies in `frames` (sorted as patterns and ranges give them; searched
    /// otherwise).
    fn index_of(&self, frame: usize) -> usize {
        self.frames
            .binary_search(&frame)
            .ok()
            .filter(|&i| self.frames[i] == frame)
            .or_else(|| self.frames.iter().position(|&x| x == frame))
            .expect("a frame of the sequence")
    }
}

/// The most frames processed at once: each job holds its frame's data in memory.
pub const MAX_JOBS: usize = 1024;

/// The frames at once asked for (`--jobs`), checked (1 to [`MAX_JOBS`]) and capped at the number of frames.
pub fn jobs(jobs: usize, frames: usize) -> Result<usize, Error> {
    if jobs == 0 || jobs > MAX_JOBS {
        return Err(Error::InvalidArgument {
            argument: "--jobs",
            reason: format!(
                "{jobs} frames at once; give 1 to {MAX_JOBS} (each job holds a frame in memory)"
            ),
        });
    }
    Ok(jobs.min(frames.max(1)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The chunks of `--shard K/N` cover the frames once, in order, contiguous, their sizes
    /// within one; bad shards and Slurm variables are refused with what is wrong.
    #[test]
    fn shards_split_the_frames_and_refuse_bad_values() {
        for n_frames in [0usize, 1, 5, 24, 25, 100] {
            let frames: Vec<usize> = (0..n_frames).map(|f| 3 * f + 1).collect();
            for count in 1..=7 {
                let parts: Vec<&[usize]> = (1..=count)
                    .map(|k| Shard::new(k, count).unwrap().of(&frames))
                    .collect();
                assert_eq!(parts.concat(), frames, "{n_frames} frames in {count}");
                let sizes: Vec<usize> = parts.iter().map(|p| p.len()).collect();
                let (lo, hi) = (sizes.iter().min().unwrap(), sizes.iter().max().unwrap());
                assert!(hi - lo <= 1, "{sizes:?}");
            }
        }
        assert_eq!(
            "2/3".parse::<Shard>().unwrap(),
            Shard { index: 2, count: 3 }
        );
        for bad in ["3/2", "0/3", "1/0", "3", "a/b", "-1/3", ""] {
            let e = bad.parse::<Shard>().unwrap_err().to_string();
            assert!(e.contains("bad shard"), "{bad}: {e}");
        }
        let env = |vars: &'static [(&'static str, &'static str)]| {
            move |name: &str| {
                vars.iter()
                    .find(|(k, _)| *k == name)
                    .map(|(_, v)| (*v).to_owned())
            }
        };
        let ok = Shard::from_slurm(env(&[
            ("SLURM_ARRAY_TASK_ID", "5"),
            ("SLURM_ARRAY_TASK_MIN", "4"),
            ("SLURM_ARRAY_TASK_COUNT", "3"),
        ]));
        assert_eq!(ok.unwrap(), Shard { index: 2, count: 3 });
        for (vars, what) in [
            (&[][..], "SLURM_ARRAY_TASK_ID is not set"),
            (
                &[
                    ("SLURM_ARRAY_TASK_ID", "x"),
                    ("SLURM_ARRAY_TASK_MIN", "1"),
                    ("SLURM_ARRAY_TASK_COUNT", "3"),
                ][..],
                "not a whole number",
            ),
            (
                &[
                    ("SLURM_ARRAY_TASK_ID", "9"),
                    ("SLURM_ARRAY_TASK_MIN", "1"),
                    ("SLURM_ARRAY_TASK_COUNT", "3"),
                ][..],
                "not among",
            ),
        ] {
            let vars: &'static [(&'static str, &'static str)] = vars;
            let e = Shard::from_slurm(env(vars)).unwrap_err().to_string();
            assert!(e.contains(what), "{e}");
        }
    }

    #[test]
    fn patterns() {
        let p = FramePattern::parse("dir/ParticleData_Fluid_{}.vtk")
            .unwrap()
            .unwrap();
        assert_eq!(p.path(7), PathBuf::from("dir/ParticleData_Fluid_7.vtk"));
        let p = FramePattern::parse("out_{:04}.ply").unwrap().unwrap();
        assert_eq!(p.path(7), PathBuf::from("out_0007.ply"));
        assert_eq!(p.path(12345), PathBuf::from("out_12345.ply"));
        assert_eq!(FramePattern::parse("plain.ply").unwrap(), None);
        for bad in ["a{.ply", "a}.ply", "a{x}.ply", "{}{}.ply", "{:zz}"] {
            assert!(FramePattern::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn ranges() {
        let r: FrameRange = "0..20".parse().unwrap();
        assert_eq!(r.frames().count(), 20);
        let r: FrameRange = "3..=5".parse().unwrap();
        assert_eq!(r.frames().collect::<Vec<_>>(), [3, 4, 5]);
        let r: FrameRange = "0..10:3".parse().unwrap();
        assert_eq!(r.frames().collect::<Vec<_>>(), [0, 3, 6, 9]);
        for bad in ["", "5", "a..b", "0..10:0", "x..=3"] {
            assert!(bad.parse::<FrameRange>().is_err(), "{bad}");
        }
        assert!(matches!(
            "5..5".parse::<FrameRange>(),
            Err(SequenceError::EmptyRange { .. })
        ));
    }

    #[test]
    fn discovers_existing_frames() {
        let dir = std::env::temp_dir().join(format!("fluid-surfels-seq-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for name in ["f_2.ply", "f_10.ply", "f_x.ply", "g_3.ply", "f_4.vtk"] {
            std::fs::write(dir.join(name), b"").unwrap();
        }
        let p = FramePattern::parse(&format!("{}/f_{{}}.ply", dir.display()))
            .unwrap()
            .unwrap();
        assert_eq!(p.existing_frames().unwrap(), [2, 10]);
        let p = FramePattern::parse(&format!("{}/h_{{}}.ply", dir.display()))
            .unwrap()
            .unwrap();
        assert!(p.existing_frames().is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A sequence over `frames` of `dir`, writing `out_{}.txt` there.
    fn sequence<'a>(input: &'a FramePattern, out: &Path, frames: Vec<usize>) -> Sequence<'a> {
        Sequence {
            input,
            frames,
            outputs: vec![
                FramePattern::parse(&format!("{}/out_{{}}.txt", out.display()))
                    .unwrap()
                    .unwrap(),
            ],
            jobs: 2,
            skip_existing: false,
            force: false,
            label: "test",
            progress: None,
            shard: None,
            warmup: 0,
        }
    }

    /// The warm-up: before each frame a job processes, the frames of the range just before it
    /// that the job has not processed (at most `warmup` of them): a job's first frame, a
    /// shard's, a frame after a skipped one; so each state sees the frames a serial run's
    /// would just before every frame it processes.
    #[test]
    fn the_runner_warms_up_jobs_shards_and_gaps() {
        let dir = tempfile::tempdir().unwrap();
        let input = FramePattern::parse(&format!("{}/in_{{}}.txt", dir.path().display()))
            .unwrap()
            .unwrap();
        // (processed frame, the frames the state saw before it: warm-ups and processed ones)
        let run = |seq: &Sequence<'_>| -> Vec<(usize, Vec<String>)> {
            seq.run_warm(
                || Ok(Vec::new()),
                |seen: &mut Vec<String>, f| {
                    seen.push(format!("w{f}"));
                    Ok(())
                },
                |seen: &mut Vec<String>, f| {
                    let before = seen.clone();
                    seen.push(format!("p{f}"));
                    Ok((f, before))
                },
            )
            .unwrap()
            .results
        };
        let mut seq = sequence(&input, dir.path(), (0..10).collect());
        seq.warmup = 3;
        let r = run(&seq);
        // two jobs: 0..5 and 5..10; the second warms up on 2, 3, 4
        assert_eq!(r[0].1, Vec::<String>::new());
        assert_eq!(r[5].1, ["w2", "w3", "w4"]);
        assert_eq!(r[6].1, ["w2", "w3", "w4", "p5"]);
        // a skipped frame inside a job's run is warmed up on
        std::fs::write(dir.path().join("out_7.txt"), "done").unwrap();
        seq.skip_existing = true;
        let r = run(&seq);
        let eight = r.iter().find(|(f, _)| *f == 8).unwrap();
        assert_eq!(eight.1.last().map(String::as_str), Some("w7"));
        // the second of two shards, one job: frames 5..10, warmed up on 2, 3, 4
        seq.skip_existing = false;
        seq.force = true;
        seq.jobs = 1;
        seq.shard = Some(Shard::new(2, 2).unwrap());
        let r = run(&seq);
        assert_eq!(r.iter().map(|x| x.0).collect::<Vec<_>>(), [5, 6, 7, 8, 9]);
        assert_eq!(r[0].1, ["w2", "w3", "w4"]);
        // no warm-up: nothing before a job's first frame
        seq.warmup = 0;
        assert!(run(&seq)[0].1.is_empty());
    }

    /// The runner: results in frame order whatever the jobs, each run's state used in frame
    /// order, progress told once per frame; existing outputs skipped or refused before any
    /// work; the first error stops the run.
    #[test]
    fn the_runner_keeps_frame_order_skips_refuses_and_stops() {
        use std::sync::atomic::AtomicUsize;
        let dir = tempfile::tempdir().unwrap();
        let input = FramePattern::parse(&format!("{}/in_{{}}.txt", dir.path().display()))
            .unwrap()
            .unwrap();
        let told = Mutex::new(Vec::new());
        let mut seq = sequence(&input, dir.path(), (0..7).collect());
        seq.progress = Some(Box::new(|p| told.lock().unwrap().push(p)));
        // each state records the frames it saw, in the order it saw them
        let run = seq
            .run(
                || Ok(Vec::new()),
                |seen: &mut Vec<usize>, f| {
                    seen.push(f);
                    Ok((f, seen.clone()))
                },
            )
            .unwrap();
        assert_eq!(run.jobs, 2);
        assert_eq!(
            run.results.iter().map(|r| r.0).collect::<Vec<_>>(),
            (0..7).collect::<Vec<_>>()
        );
        for (f, seen) in &run.results {
            assert_eq!(seen.last(), Some(f));
            assert!(seen.windows(2).all(|w| w[1] == w[0] + 1), "{seen:?}");
        }
        drop(seq);
        let told = told.into_inner().unwrap();
        assert_eq!(told.first(), Some(&Progress::Start(7)));
        assert_eq!(told.last(), Some(&Progress::End));
        assert_eq!(told.iter().filter(|&&p| p == Progress::Frame).count(), 7);

        // frames 2 and 5 written: skipped with skip_existing, refused without it
        for f in [2, 5] {
            std::fs::write(dir.path().join(format!("out_{f}.txt")), "done").unwrap();
        }
        let calls = AtomicUsize::new(0);
        let process = |_: &mut (), f: usize| {
            calls.fetch_add(1, Ordering::SeqCst);
            Ok(f)
        };
        let mut skipping = sequence(&input, dir.path(), (0..7).collect());
        skipping.skip_existing = true;
        let run = skipping.run(|| Ok(()), process).unwrap();
        assert_eq!(run.skipped, vec![2, 5]);
        assert_eq!(run.results, vec![0, 1, 3, 4, 6]);
        calls.store(0, Ordering::SeqCst);
        let refused = sequence(&input, dir.path(), (0..7).collect()).run(|| Ok(()), process);
        assert!(refused.is_err() && calls.load(Ordering::SeqCst) == 0);

        // an error stops the run and is returned
        let failing = sequence(&input, dir.path(), vec![0, 1, 3, 4]).run(
            || Ok(()),
            |_: &mut (), f| {
                if f == 3 {
                    Err(Error::InvalidArgument {
                        argument: "frame",
                        reason: "three".into(),
                    })
                } else {
                    Ok(f)
                }
            },
        );
        assert!(failing.unwrap_err().to_string().contains("three"));
        assert!(jobs(0, 5).is_err() && jobs(MAX_JOBS + 1, 5).is_err());
        assert_eq!(jobs(8, 3).unwrap(), 3);
    }
}
