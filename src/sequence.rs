//! Numbered frame sequences: file name patterns (`dir/frame_{}.vtk`, `out_{:04}.ply`) and frame
//! ranges (`0..20`, `0..=20`, `0..100:5`), shared by every CLI subcommand.

use std::path::{Path, PathBuf};
use std::str::FromStr;

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

#[cfg(test)]
mod tests {
    use super::*;

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
}
