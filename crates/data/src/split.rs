//! Train / evaluation splits: the published protocols as presets, or explicit lists.
//!
//! | capture | train | novel view | novel pose |
//! |---|---|---|---|
//! | AvatarReX | all frames, cameras except 7 and 13 | all frames, cameras 7 and 13 | — (not defined by the dataset: give `--frames`) |
//! | THuman4.0 (subject00) | frames 0–1999, cameras except 7 | frames 0–1999, camera 7 | frames 2000–2499, camera 18 (Animatable Gaussians' evaluation) |
//! | synthetic (`f3g synth`) | first 80 % of frames, cameras except 0, 7 and 13 | same frames, cameras 0, 7 and 13 | last 20 % of frames, cameras 0, 7 and 13 |
//!
//! The synthetic capture holds out a frontal camera (0: yaw 0°, where the body faces) beside
//! AvatarReX's 7 and 13 (in the 16-camera ring behind at 157.5° and beside at −67.5°), so that
//! the evaluation sees the face; a one-camera capture holds out none.
//!
//! Preset frame ranges are cut to the frames a capture has. Missing images are skipped by the
//! loader, not by the split.

use crate::DataError;
use crate::dataset::{Dataset, Layout};

/// Which part of the protocol.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SplitKind {
    Train,
    NovelView,
    NovelPose,
}

impl std::str::FromStr for SplitKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "train" => Ok(Self::Train),
            "novel-view" => Ok(Self::NovelView),
            "novel-pose" => Ok(Self::NovelPose),
            _ => Err(format!(
                "unknown split {}: expected train, novel-view or novel-pose",
                f3g_io::quoted(s)
            )),
        }
    }
}

impl std::fmt::Display for SplitKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Train => "train",
            Self::NovelView => "novel-view",
            Self::NovelPose => "novel-pose",
        })
    }
}

/// Cameras and frames of a split.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Split {
    pub cameras: Vec<usize>,
    pub frames: Vec<usize>,
}

/// The family of protocols a capture follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Protocol {
    AvatarRex,
    Thuman4,
    Synthetic,
}

/// Marker file written by `f3g synth`.
pub const SYNTH_MARKER: &str = "synth.json";

impl Protocol {
    /// The protocol of an opened capture.
    pub fn of(ds: &Dataset) -> Self {
        match ds.layout {
            _ if ds.root.join(SYNTH_MARKER).exists() => Self::Synthetic,
            Layout::AvatarRex => Self::AvatarRex,
            Layout::Thuman4 => Self::Thuman4,
        }
    }
}

/// The synthetic ring's held-out cameras: frontal (0), behind (7) and beside (13).
pub const SYNTH_HELD_OUT: [usize; 3] = [0, 7, 13];

/// The preset split of `kind` for a capture with `cameras` cameras and `frames` frames.
pub fn preset(
    protocol: Protocol,
    kind: SplitKind,
    cameras: usize,
    frames: usize,
) -> Result<Split, DataError> {
    let all_but = |held: &[usize]| {
        (0..cameras)
            .filter(|c| !held.contains(c))
            .collect::<Vec<_>>()
    };
    let only = |keep: &[usize]| {
        keep.iter()
            .copied()
            .filter(|&c| c < cameras)
            .collect::<Vec<_>>()
    };
    let range = |a: usize, b: usize| (a.min(frames)..b.min(frames)).collect::<Vec<_>>();
    let split = match (protocol, kind) {
        (Protocol::AvatarRex, SplitKind::Train) => Split {
            cameras: all_but(&[7, 13]),
            frames: range(0, frames),
        },
        (Protocol::AvatarRex, SplitKind::NovelView) => Split {
            cameras: only(&[7, 13]),
            frames: range(0, frames),
        },
        (Protocol::AvatarRex, SplitKind::NovelPose) => {
            return Err(DataError::Invalid(
                "AvatarReX defines no novel-pose split: give the frames explicitly (--frames A..B)"
                    .into(),
            ));
        }
        (Protocol::Thuman4, SplitKind::Train) => Split {
            cameras: all_but(&[7]),
            frames: range(0, 2000),
        },
        (Protocol::Thuman4, SplitKind::NovelView) => Split {
            cameras: only(&[7]),
            frames: range(0, 2000),
        },
        (Protocol::Thuman4, SplitKind::NovelPose) => Split {
            cameras: only(&[18]),
            frames: range(2000, 2500),
        },
        (Protocol::Synthetic, kind) => {
            let cut = (frames * 4).div_ceil(5);
            let held: &[usize] = if cameras > 1 { &SYNTH_HELD_OUT } else { &[] };
            match kind {
                SplitKind::Train => Split {
                    cameras: all_but(held),
                    frames: range(0, cut),
                },
                SplitKind::NovelView => Split {
                    cameras: only(held),
                    frames: range(0, cut),
                },
                SplitKind::NovelPose => Split {
                    cameras: only(held),
                    frames: range(cut, frames),
                },
            }
        }
    };
    if split.cameras.is_empty() || split.frames.is_empty() {
        return Err(DataError::Invalid(format!(
            "the {kind:?} split of this capture ({cameras} cameras, {frames} frames) is empty"
        )));
    }
    Ok(split)
}

/// Parses `A..B` (end exclusive) or a comma-separated list.
pub fn parse_indices(text: &str, limit: usize, what: &str) -> Result<Vec<usize>, DataError> {
    let bad = |m: String| DataError::Invalid(format!("{what} {}: {m}", f3g_io::quoted(text)));
    let out: Vec<usize> = if let Some((a, b)) = text.split_once("..") {
        let a: usize = if a.is_empty() {
            0
        } else {
            a.parse().map_err(|_| bad("bad start".into()))?
        };
        let b: usize = if b.is_empty() {
            limit
        } else {
            b.parse().map_err(|_| bad("bad end".into()))?
        };
        // Checked before the range is collected: `0..99999999999` must not allocate.
        if b > limit {
            return Err(bad(format!(
                "ends at {b}, out of range (there are {limit})"
            )));
        }
        (a..b).collect()
    } else {
        text.split(',')
            .map(|s| {
                s.trim()
                    .parse::<usize>()
                    .map_err(|_| bad(format!("{} is not an index", f3g_io::quoted(s))))
            })
            .collect::<Result<_, _>>()?
    };
    if out.is_empty() {
        return Err(bad("selects nothing".into()));
    }
    if let Some(&i) = out.iter().find(|&&i| i >= limit) {
        return Err(bad(format!("{i} is out of range (there are {limit})")));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_select_the_documented_cameras_and_frames() {
        let s = preset(Protocol::AvatarRex, SplitKind::Train, 16, 2001).unwrap();
        assert_eq!(
            s.cameras,
            vec![0, 1, 2, 3, 4, 5, 6, 8, 9, 10, 11, 12, 14, 15]
        );
        assert_eq!(s.frames.len(), 2001);
        assert_eq!(
            preset(Protocol::AvatarRex, SplitKind::NovelView, 16, 2001)
                .unwrap()
                .cameras,
            vec![7, 13]
        );
        assert!(preset(Protocol::AvatarRex, SplitKind::NovelPose, 16, 2001).is_err());
        let t = preset(Protocol::Thuman4, SplitKind::Train, 24, 2500).unwrap();
        assert_eq!(t.cameras.len(), 23);
        assert!(!t.cameras.contains(&7));
        assert_eq!(
            (t.frames[0], *t.frames.last().unwrap(), t.frames.len()),
            (0, 1999, 2000)
        );
        let v = preset(Protocol::Thuman4, SplitKind::NovelView, 24, 2500).unwrap();
        assert_eq!((v.cameras, v.frames.len()), (vec![7], 2000));
        let p = preset(Protocol::Thuman4, SplitKind::NovelPose, 24, 2500).unwrap();
        assert_eq!(
            (p.cameras, p.frames[0], p.frames.len()),
            (vec![18], 2000, 500)
        );
        let syn = preset(Protocol::Synthetic, SplitKind::NovelPose, 16, 50).unwrap();
        assert_eq!(
            (syn.cameras, syn.frames[0], syn.frames.len()),
            (vec![0, 7, 13], 40, 10)
        );
        assert_eq!(
            preset(Protocol::Synthetic, SplitKind::NovelView, 16, 50)
                .unwrap()
                .cameras,
            vec![0, 7, 13]
        );
        assert_eq!(
            preset(Protocol::Synthetic, SplitKind::Train, 16, 50)
                .unwrap()
                .cameras,
            vec![1, 2, 3, 4, 5, 6, 8, 9, 10, 11, 12, 14, 15]
        );
        // Fewer cameras: those that exist; one camera trains and holds out none.
        assert_eq!(
            preset(Protocol::Synthetic, SplitKind::NovelView, 4, 50)
                .unwrap()
                .cameras,
            vec![0]
        );
        assert_eq!(
            preset(Protocol::Synthetic, SplitKind::Train, 1, 50)
                .unwrap()
                .cameras,
            vec![0]
        );
        assert_eq!(
            preset(Protocol::Synthetic, SplitKind::Train, 16, 50)
                .unwrap()
                .frames
                .len(),
            40
        );
    }

    #[test]
    fn explicit_indices() {
        assert_eq!(parse_indices("2..5", 10, "frames").unwrap(), vec![2, 3, 4]);
        assert_eq!(
            parse_indices("0,3,9", 10, "cameras").unwrap(),
            vec![0, 3, 9]
        );
        assert!(
            parse_indices("8..12", 10, "frames")
                .unwrap_err()
                .to_string()
                .contains("out of range")
        );
        assert!(parse_indices("a,b", 10, "cameras").is_err());
        // Refused before the range is collected (this one would need 800 GB).
        let e = parse_indices("0..99999999999", 10, "frames").unwrap_err();
        assert!(e.to_string().contains("99999999999"), "{e}");
        // A huge input is quoted briefly, with its length.
        let long = "x".repeat(5_000_000);
        let e = parse_indices(&long, 10, "frames").unwrap_err().to_string();
        assert!(
            e.len() < 600 && e.contains("5000000 bytes"),
            "{}",
            &e[..e.len().min(600)]
        );
    }
}
