//! Momentum parameter transforms and the `.model` text format.
//!
//! A parameter transform maps model parameters `p` to joint parameters
//! `j = M p + c` with a sparse `M` of size `(7·joints) × parameters` (rows are
//! `joint·7 + channel`, channels `tx ty tz rx ry rz sc`).
//!
//! `.model` files (Momentum Model Definition V1.0) hold it as text:
//!
//! ```text
//! Momentum Model Definition V1.0
//! [ParameterTransform]
//! root.tx = 1.0*root_tx            # weight*parameter, '+'-separated terms
//! l_knee.rx = 1.0*knee_l + 0.1     # a bare number is the constant offset
//! r_knee.rx = -1.0*l_knee.rx       # joint.channel copies that row's terms, scaled
//! [ParameterSets]
//! parameterset legs knee_l
//! ```
//!
//! As in Momentum: parameters are numbered in order of first appearance, `#` starts a comment,
//! lines without `=` in `[ParameterTransform]` are skipped with a warning, and the sections
//! `[PoseConstraints]` and `[Limits]` are read past (limits do not change evaluation).
//! Unknown joints or channels and unparsable numbers or terms are errors naming the line.

use std::collections::BTreeMap;
use std::path::Path;

use crate::RigError;
use crate::skeleton::{PARAMS_PER_JOINT, Skeleton};

/// Channel names of the seven joint parameters.
pub const CHANNELS: [&str; PARAMS_PER_JOINT] = ["tx", "ty", "tz", "rx", "ry", "rz", "sc"];

/// Sparse linear map from model parameters to joint parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct ParameterTransform {
    /// Model parameter names, in column order.
    pub names: Vec<String>,
    /// `(row, column, weight)` with `row = joint·7 + channel`; duplicates add up.
    pub entries: Vec<(u32, u32, f32)>,
    /// Constant joint parameters, one per row.
    pub offsets: Vec<f32>,
}

impl ParameterTransform {
    /// A transform with no parameters over `joints` joints.
    pub fn empty(joints: usize) -> Self {
        Self {
            names: Vec::new(),
            entries: Vec::new(),
            offsets: vec![0.0; joints * PARAMS_PER_JOINT],
        }
    }

    /// Adds a parameter driving the given `(joint, channel, weight)` rows; returns its index.
    pub fn add_parameter(
        &mut self,
        name: impl Into<String>,
        rows: &[(usize, usize, f32)],
    ) -> usize {
        let col = self.names.len() as u32;
        self.names.push(name.into());
        for &(joint, channel, weight) in rows {
            self.entries
                .push(((joint * PARAMS_PER_JOINT + channel) as u32, col, weight));
        }
        col as usize
    }

    /// Number of model parameters.
    pub fn len(&self) -> usize {
        self.names.len()
    }

    /// True without parameters.
    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }

    /// Index of the parameter called `name`.
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// Joint parameters `M p + c` for model parameters `p`.
    pub fn apply(&self, params: &[f32]) -> Result<Vec<[f32; PARAMS_PER_JOINT]>, RigError> {
        if params.len() != self.names.len() {
            return Err(RigError::Params(format!(
                "{} model parameters given, the model has {}",
                params.len(),
                self.names.len()
            )));
        }
        if let Some(i) = params.iter().position(|v| !v.is_finite()) {
            return Err(RigError::Params(format!(
                "model parameter {i} (`{}`) is not finite",
                self.names[i]
            )));
        }
        let mut rows = self.offsets.clone();
        for &(row, col, w) in &self.entries {
            rows[row as usize] += w * params[col as usize];
        }
        Ok(rows
            .chunks_exact(PARAMS_PER_JOINT)
            .map(|c| c.try_into().expect("7 channels"))
            .collect())
    }
}

/// The contents of a `.model` file.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelDefinition {
    pub transform: ParameterTransform,
    /// Named subsets of parameters (`[ParameterSets]`).
    pub parameter_sets: BTreeMap<String, Vec<usize>>,
    /// Lines that were skipped, with the reason, as Momentum warns about them.
    pub warnings: Vec<String>,
}

/// Reads a `.model` file for `skeleton`.
pub fn read_model_file(path: &Path, skeleton: &Skeleton) -> Result<ModelDefinition, RigError> {
    let text = std::fs::read_to_string(path).map_err(|e| RigError::file(path, e))?;
    parse_model(&text, skeleton, path)
}

/// Parses `.model` text; `file` only labels errors.
pub fn parse_model(
    text: &str,
    skeleton: &Skeleton,
    file: &Path,
) -> Result<ModelDefinition, RigError> {
    let err = |line: usize, reason: String| RigError::Line {
        file: file.to_path_buf(),
        line,
        reason,
    };
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.split('#').next().unwrap_or("").trim()));
    match lines.by_ref().find(|(_, l)| !l.is_empty()) {
        Some((_, "Momentum Model Definition V1.0")) => {}
        Some((n, other)) => {
            return Err(err(
                n,
                format!(
                    "expected `Momentum Model Definition V1.0`, found {}",
                    f3g_io::quoted(other)
                ),
            ));
        }
        None => {
            return Err(err(
                1,
                "empty file: expected `Momentum Model Definition V1.0`".into(),
            ));
        }
    }

    let rows = skeleton.len() * PARAMS_PER_JOINT;
    let mut transform = ParameterTransform {
        names: Vec::new(),
        entries: Vec::new(),
        offsets: vec![0.0; rows],
    };
    let mut parameter_sets = BTreeMap::new();
    let mut warnings = Vec::new();
    let mut section = String::new();
    for (n, line) in lines {
        if line.is_empty() {
            continue;
        }
        if let Some(name) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            section = name.to_string();
            continue;
        }
        match section.as_str() {
            "ParameterTransform" => {
                let Some((lhs, rhs)) = line.split_once('=').filter(|(_, r)| !r.contains('='))
                else {
                    warnings.push(format!(
                        "line {n}: skipped, expected `joint.channel = expression`: {}",
                        f3g_io::quoted(line)
                    ));
                    continue;
                };
                let row = channel_row(lhs.trim(), skeleton).map_err(|e| err(n, e))?;
                parse_expression(rhs, row, skeleton, &mut transform).map_err(|e| err(n, e))?;
            }
            "ParameterSets" => {
                let words: Vec<&str> = line.split_whitespace().collect();
                if words.first() != Some(&"parameterset") || words.len() < 2 {
                    warnings.push(format!(
                        "line {n}: skipped, expected `parameterset name params...`: {line}"
                    ));
                    continue;
                }
                let members = words[2..]
                    .iter()
                    .map(|p| {
                        transform.index_of(p).ok_or_else(|| {
                            err(
                                n,
                                format!(
                                    "parameter set `{}` names unknown parameter `{p}`",
                                    words[1]
                                ),
                            )
                        })
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                parameter_sets.insert(words[1].to_string(), members);
            }
            "PoseConstraints" | "Limits" => {}
            "" => warnings.push(format!("line {n}: skipped, not inside a section: {line}")),
            other => warnings.push(format!("line {n}: skipped, unknown section [{other}]")),
        }
    }
    transform.entries.retain(|e| e.2 != 0.0);
    Ok(ModelDefinition {
        transform,
        parameter_sets,
        warnings,
    })
}

/// `joint.channel` → row index.
fn channel_row(text: &str, skeleton: &Skeleton) -> Result<usize, String> {
    let (joint, channel) = text
        .split_once('.')
        .ok_or_else(|| format!("{} is not `joint.channel`", f3g_io::quoted(text)))?;
    let j = skeleton
        .index_of(joint.trim())
        .ok_or_else(|| format!("unknown joint {}", f3g_io::quoted(joint.trim())))?;
    let c = CHANNELS
        .iter()
        .position(|c| *c == channel.trim())
        .ok_or_else(|| {
            format!(
                "unknown channel `{}` (expected one of {})",
                channel.trim(),
                CHANNELS.join(", ")
            )
        })?;
    Ok(j * PARAMS_PER_JOINT + c)
}

fn parse_expression(
    rhs: &str,
    row: usize,
    skeleton: &Skeleton,
    t: &mut ParameterTransform,
) -> Result<(), String> {
    for term in rhs.split('+').map(str::trim).filter(|s| !s.is_empty()) {
        let factors: Vec<&str> = term.split('*').map(str::trim).collect();
        let number = |s: &str| {
            s.parse::<f32>().map_err(|_| {
                format!(
                    "{} is not a number in term {}",
                    f3g_io::quoted(s),
                    f3g_io::quoted(term)
                )
            })
        };
        match factors.as_slice() {
            [constant] => t.offsets[row] = number(constant)?,
            [weight, name] => {
                let w = number(weight)?;
                if let Some(col) = t.index_of(name) {
                    t.entries.push((row as u32, col as u32, w));
                } else if let Some(referenced) = joint_reference(name, skeleton)? {
                    let copied: Vec<_> = t
                        .entries
                        .iter()
                        .filter(|e| e.0 as usize == referenced)
                        .map(|e| (row as u32, e.1, e.2 * w))
                        .collect();
                    t.entries.extend(copied);
                } else {
                    t.names.push(name.to_string());
                    t.entries.push((row as u32, (t.names.len() - 1) as u32, w));
                }
            }
            _ => {
                return Err(format!(
                    "malformed term {}: expected `weight*parameter` or a number",
                    f3g_io::quoted(term)
                ));
            }
        }
    }
    Ok(())
}

/// `Some(row)` when `name` is `joint.channel` of a known joint; an error for a known joint
/// with an unknown channel; `None` for an ordinary (new) parameter name.
fn joint_reference(name: &str, skeleton: &Skeleton) -> Result<Option<usize>, String> {
    let Some((joint, _)) = name.split_once('.') else {
        return Ok(None);
    };
    if skeleton.index_of(joint).is_none() {
        return Ok(None);
    }
    channel_row(name, skeleton).map(Some)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skeleton::Joint;
    use glam::{Quat, Vec3};

    fn skeleton() -> Skeleton {
        let joint = |name: &str, parent| Joint {
            name: name.into(),
            parent,
            offset: Vec3::ZERO,
            pre_rotation: Quat::IDENTITY,
        };
        Skeleton::new(vec![
            joint("root", None),
            joint("l_knee", Some(0)),
            joint("r_knee", Some(0)),
        ])
        .unwrap()
    }

    const MODEL: &str = "# leading comment\nMomentum Model Definition V1.0\n\n[ParameterTransform]\nroot.tx = 1.0*root_tx\nroot.ry = 0.5*turn + 0.25 # half a turn\nl_knee.rx = 1.0*knee_l + 0.1\nr_knee.rx = -1.0*l_knee.rx + 2.0*extra\nthis line is ignored\n[ParameterSets]\nparameterset legs knee_l extra\n[Limits]\nlimit knee_l minmax [0, 2] 1.0\n";

    #[test]
    fn parses_terms_offsets_references_and_sets() {
        let m = parse_model(MODEL, &skeleton(), Path::new("t.model")).unwrap();
        let t = &m.transform;
        assert_eq!(t.names, ["root_tx", "turn", "knee_l", "extra"]);
        assert_eq!(t.offsets[4], 0.25);
        assert_eq!(t.offsets[7 + 3], 0.1);
        // The reference copies l_knee.rx's terms scaled by -1 (not its constant).
        let joints = t.apply(&[0.3, 1.0, 0.7, 0.05]).unwrap();
        assert_eq!(joints[0][0], 0.3);
        assert_eq!(joints[0][4], 0.75);
        assert!((joints[1][3] - 0.8).abs() < 1e-6);
        assert!((joints[2][3] - (-0.7 + 0.1)).abs() < 1e-6);
        assert_eq!(m.parameter_sets["legs"], vec![2, 3]);
        assert_eq!(m.warnings.len(), 1);
    }

    #[test]
    fn malformed_lines_name_the_line() {
        let s = skeleton();
        let f = Path::new("bad.model");
        let e = parse_model(
            "Momentum Model Definition V1.0\n[ParameterTransform]\nelbow.rx = 1.0*a\n",
            &s,
            f,
        )
        .unwrap_err();
        assert_eq!(e.to_string(), "bad.model:3: unknown joint `elbow`");
        let e = parse_model(
            "Momentum Model Definition V1.0\n[ParameterTransform]\nroot.qx = 1.0*a\n",
            &s,
            f,
        )
        .unwrap_err();
        assert!(e.to_string().contains(":3: unknown channel `qx`"), "{e}");
        let e = parse_model(
            "Momentum Model Definition V1.0\n[ParameterTransform]\nroot.rx = one*a\n",
            &s,
            f,
        )
        .unwrap_err();
        assert!(e.to_string().contains("`one` is not a number"), "{e}");
        let e = parse_model(
            "Momentum Model Definition V1.0\n[ParameterTransform]\nroot.rx = 1*a*b\n",
            &s,
            f,
        )
        .unwrap_err();
        assert!(e.to_string().contains("malformed term"), "{e}");
        let e = parse_model(
            "Momentum Model Definition V1.0\n[ParameterTransform]\nroot.rx = 1*root.zz\n",
            &s,
            f,
        )
        .unwrap_err();
        assert!(e.to_string().contains("unknown channel `zz`"), "{e}");
        let e = parse_model("Model V2\n", &s, f).unwrap_err();
        assert!(
            e.to_string()
                .contains("bad.model:1: expected `Momentum Model Definition V1.0`"),
            "{e}"
        );
        let e = parse_model(
            "Momentum Model Definition V1.0\n[ParameterSets]\nparameterset x nope\n",
            &s,
            f,
        )
        .unwrap_err();
        assert!(e.to_string().contains("unknown parameter `nope`"), "{e}");
    }

    #[test]
    fn apply_checks_length_and_finiteness() {
        let m = parse_model(MODEL, &skeleton(), Path::new("t.model")).unwrap();
        assert!(
            m.transform
                .apply(&[0.0; 3])
                .unwrap_err()
                .to_string()
                .contains("3 model parameters given")
        );
        assert!(
            m.transform
                .apply(&[0.0, f32::NAN, 0.0, 0.0])
                .unwrap_err()
                .to_string()
                .contains("`turn`")
        );
    }
}
