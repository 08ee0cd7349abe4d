//! The architecture's invariants (ARCHITECTURE.md), checked on the sources: each test reads
//! the workspace's `Cargo.toml`s and `.rs` files (test modules and `tests/` left out) and fails
//! naming the file and line that breaks a rule.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The crates, bottom of the graph first, with the workspace crates each may depend on.
const LAYERS: [(&str, &[&str]); 11] = [
    ("io", &[]),
    ("camera", &[]),
    ("testkit", &["io"]),
    ("rig", &["io"]),
    ("motion", &["io", "rig"]),
    ("splat", &["io", "camera"]),
    ("template", &["io", "camera", "rig"]),
    ("data", &["io", "camera", "rig", "template"]),
    ("nets", &["io"]),
    (
        "avatar",
        &[
            "io", "camera", "rig", "motion", "splat", "template", "data", "nets",
        ],
    ),
    (
        "cli",
        &[
            "io", "camera", "rig", "motion", "splat", "template", "data", "nets", "avatar",
        ],
    ),
];

/// Crates that may use Burn (the others are plain Rust over `f3g-io`).
const BURN: [&str; 4] = ["splat", "nets", "avatar", "cli"];

/// The `[dependencies]` entries of a crate's manifest (not dev- or build-dependencies).
fn dependencies(krate: &str) -> Vec<String> {
    manifest_entries(krate, "[dependencies]")
}

/// The entry names of a section (`[dependencies]`, `[dev-dependencies]`) of a crate's manifest.
fn manifest_entries(krate: &str, wanted: &str) -> Vec<String> {
    let text =
        std::fs::read_to_string(workspace().join("crates").join(krate).join("Cargo.toml")).unwrap();
    let mut section = String::new();
    let mut out = Vec::new();
    for line in text.lines() {
        let line = line.trim();
        if line.starts_with('[') {
            section = line.to_string();
        } else if section == wanted
            && let Some((name, _)) = line.split_once(['=', '.'])
            && !line.starts_with('#')
        {
            out.push(name.trim().to_string());
        }
    }
    out
}

/// A source file's code lines with their numbers: comments and `#[cfg(test)]` items left out
/// (an item ends where its braces close).
fn code_lines(path: &Path) -> Vec<(usize, String)> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut out = Vec::new();
    let (mut in_test, mut depth, mut opened) = (false, 0i64, false);
    for (i, line) in text.lines().enumerate() {
        if line.trim() == "#[cfg(test)]" {
            (in_test, depth, opened) = (true, 0, false);
            continue;
        }
        if in_test {
            for c in line.chars() {
                match c {
                    '{' => (depth, opened) = (depth + 1, true),
                    '}' => depth -= 1,
                    _ => {}
                }
            }
            // The item ends where its braces close, or at its `;` when it has none.
            let ended = if opened {
                depth <= 0
            } else {
                line.trim_end().ends_with(';')
            };
            in_test = !ended;
            continue;
        }
        if !line.trim_start().starts_with("//") {
            out.push((i + 1, line.to_string()));
        }
    }
    out
}

/// Every `.rs` file under `dir`.
fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// The library sources of a crate.
fn sources(krate: &str) -> Vec<PathBuf> {
    rust_files(&workspace().join("crates").join(krate).join("src"))
}

/// `file:line: text` for every code line of `files` that contains one of `needles`.
fn find(files: &[PathBuf], needles: &[&str]) -> Vec<String> {
    let root = workspace();
    let mut out = Vec::new();
    for f in files {
        let rel = f.strip_prefix(&root).unwrap_or(f).display().to_string();
        for (i, l) in code_lines(f) {
            if needles.iter().any(|n| l.contains(n)) {
                out.push(format!("{rel}:{i}: {}", l.trim()));
            }
        }
    }
    out
}

#[test]
fn crates_depend_only_on_crates_below_them_and_burn_stays_above_the_data() {
    let mut broken = Vec::new();
    for (krate, allowed) in LAYERS {
        for dep in dependencies(krate) {
            if let Some(other) = dep.strip_prefix("f3g-")
                && !allowed.contains(&other)
            {
                broken.push(format!("{krate} depends on f3g-{other}"));
            }
            if dep.starts_with("burn") && !BURN.contains(&krate) {
                broken.push(format!("{krate} depends on {dep}"));
            }
        }
    }
    let crates: BTreeSet<String> = std::fs::read_dir(workspace().join("crates"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    let layered: BTreeSet<String> = LAYERS.iter().map(|(k, _)| k.to_string()).collect();
    assert_eq!(crates, layered, "every crate has its place in LAYERS");
    let architecture = std::fs::read_to_string(workspace().join("ARCHITECTURE.md")).unwrap();
    for krate in &crates {
        if !architecture.contains(&format!("`crates/{krate}`")) {
            broken.push(format!("ARCHITECTURE.md does not describe crates/{krate}"));
        }
    }
    assert!(broken.is_empty(), "{broken:#?}");
}

#[test]
fn only_the_rig_crate_knows_joint_names() {
    let mut names: BTreeSet<String> = f3g_rig::builtin::load()
        .unwrap()
        .rig
        .skeleton
        .joints()
        .iter()
        .map(|j| j.name.clone())
        .collect();
    names.extend(f3g_rig::smplx::JOINT_NAMES.iter().map(|n| n.to_string()));
    let channels = ["tx", "ty", "tz", "rx", "ry", "rz", "sc"];
    let mut broken = Vec::new();
    for (krate, _) in LAYERS.iter().filter(|(k, _)| *k != "rig") {
        for file in sources(krate) {
            for (i, line) in code_lines(&file) {
                // The string literals of the line.
                for (k, literal) in line.split('"').enumerate() {
                    let joint = literal
                        .rsplit_once('_')
                        .filter(|(_, c)| channels.contains(c))
                        .map_or(literal, |(j, _)| j);
                    if k % 2 == 1 && names.contains(joint) {
                        broken.push(format!(
                            "{krate}/{}:{i}: \"{literal}\"",
                            file.file_name().unwrap().to_string_lossy()
                        ));
                    }
                }
            }
        }
    }
    assert!(
        broken.is_empty(),
        "joint names outside f3g-rig: {broken:#?}"
    );
}

/// The module path of a source file under `crates/avatar/src` (`model/nets.rs` →
/// `["model", "nets"]`, `model/mod.rs` → `["model"]`).
fn module_path(src: &Path, file: &Path) -> Vec<String> {
    let mut parts: Vec<String> = file
        .strip_prefix(src)
        .unwrap()
        .with_extension("")
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    if parts.last().is_some_and(|p| p == "mod" || p == "lib") {
        parts.pop();
    }
    parts
}

/// Every crate-relative path in `code` (`crate::…`, `super::…`, `self::…`, across lines) as
/// (byte offset, the crate-root module it names), resolved from the module `module`:
/// `super::super::train::X` in `model/nets.rs` names `train`; a braced group names each of
/// its items (`use crate::{model, train::Trainer}` names `model` and `train`).
fn crate_paths(code: &str, module: &[String]) -> Vec<(usize, String)> {
    let ident = |s: &str| -> String {
        s.chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect()
    };
    let mut out = Vec::new();
    for (start, _) in code.char_indices() {
        let first = ident(&code[start..]);
        let follows_path = code[..start]
            .chars()
            .next_back()
            .is_some_and(|c| c.is_alphanumeric() || c == '_' || c == ':');
        if follows_path || !matches!(first.as_str(), "crate" | "super" | "self") {
            continue;
        }
        let mut resolved: Vec<String> = match first.as_str() {
            "crate" => Vec::new(),
            "super" => module[..module.len().saturating_sub(1)].to_vec(),
            _ => module.to_vec(),
        };
        let mut rest = &code[start + first.len()..];
        let mut is_path = false;
        while let Some(after) = rest.trim_start().strip_prefix("::") {
            is_path = true;
            let after = after.trim_start();
            if let Some(group) = after.strip_prefix('{') {
                let mut depth = 0;
                let mut items = vec![String::new()];
                for c in group.chars() {
                    match c {
                        '{' => depth += 1,
                        '}' if depth == 0 => break,
                        '}' => depth -= 1,
                        ',' if depth == 0 => {
                            items.push(String::new());
                            continue;
                        }
                        _ => {}
                    }
                    items.last_mut().unwrap().push(c);
                }
                for item in items
                    .iter()
                    .map(|i| ident(i.trim()))
                    .filter(|i| !i.is_empty())
                {
                    let root = resolved.first().cloned().unwrap_or(item);
                    out.push((start, root));
                }
                resolved.clear();
                break;
            }
            let segment = ident(after);
            if segment.is_empty() {
                break;
            }
            if segment == "super" {
                resolved.pop();
            } else {
                resolved.push(segment.clone());
            }
            rest = &after[segment.len()..];
        }
        if let (true, Some(root)) = (is_path, resolved.first()) {
            out.push((start, root.clone()));
        }
    }
    out
}

/// `file:line: text` for every code line of the avatar crate's `folder` that names a module of
/// `forbidden` at the crate root, in any spelling ([`crate_paths`]), or one of `words`.
fn folder_imports(folder: &str, forbidden: &[&str], words: &[&str]) -> Vec<String> {
    let root = workspace();
    let src = root.join("crates/avatar/src");
    let mut out = Vec::new();
    for f in rust_files(&src.join(folder)) {
        let rel = f.strip_prefix(&root).unwrap_or(&f).display().to_string();
        let lines = code_lines(&f);
        // The code lines joined, and where each begins.
        let mut code = String::new();
        let mut starts = Vec::new();
        for (_, l) in &lines {
            starts.push(code.len());
            code.push_str(l);
            code.push('\n');
        }
        let mut bad: BTreeSet<usize> = crate_paths(&code, &module_path(&src, &f))
            .into_iter()
            .filter(|(_, m)| forbidden.contains(&m.as_str()))
            .map(|(offset, _)| starts.partition_point(|&s| s <= offset) - 1)
            .collect();
        for (k, (_, l)) in lines.iter().enumerate() {
            let mut tokens = l.split(|c: char| !(c.is_alphanumeric() || c == '_'));
            if tokens.any(|t| words.contains(&t)) {
                bad.insert(k);
            }
        }
        for k in bad {
            let (i, l) = &lines[k];
            out.push(format!("{rel}:{i}: {}", l.trim()));
        }
    }
    out
}

#[test]
fn the_avatar_model_and_inference_never_import_training() {
    // Training's types may not be named either (were they re-exported elsewhere).
    let words = ["TrainConfig", "Trainer"];
    let mut broken = folder_imports("model", &["train", "infer"], &words);
    broken.extend(folder_imports("infer", &["train"], &words));
    assert!(broken.is_empty(), "{broken:#?}");
}

#[test]
fn crate_paths_resolve_every_spelling_of_a_module() {
    let module = ["infer", "bake", "sampling"].map(String::from);
    let roots = |code: &str| -> Vec<String> {
        crate_paths(code, &module)
            .into_iter()
            .map(|(_, m)| m)
            .collect()
    };
    assert_eq!(roots("use crate::train::Trainer;"), ["train"]);
    assert_eq!(
        roots("use crate::{model::Setup, train};"),
        ["model", "train"]
    );
    assert_eq!(
        roots("use crate::{\n    AvatarError,\n    train::{self, Stage},\n};"),
        ["AvatarError", "train"]
    );
    assert_eq!(roots("use super::super::super::train::Stage;"), ["train"]);
    assert_eq!(
        roots("use super::super::super::{train, model};"),
        ["train", "model"]
    );
    assert_eq!(
        roots("use super::{correctives, influences};"),
        ["infer", "infer"]
    );
    assert_eq!(
        roots("let c = crate::train::TrainConfig::cpu();"),
        ["train"]
    );
    assert!(roots("self.tables.inputs(); pub(super) fn f() {}").is_empty());
}

#[test]
fn no_crate_below_the_avatar_knows_burns_autodiff_but_the_ops_graph_nodes() {
    let mut files: Vec<PathBuf> = ["io", "camera", "rig", "template", "data"]
        .iter()
        .flat_map(|k| sources(k))
        .collect();
    // The backend extensions (the splat op, the convolution, the fused element-wise ops) record
    // their own graph nodes, and the gate nodes the last two share.
    files.extend(
        sources("splat")
            .into_iter()
            .filter(|f| !f.ends_with("op/autodiff.rs")),
    );
    files.extend(sources("nets").into_iter().filter(|f| {
        !f.ends_with("conv/autodiff.rs")
            && !f.ends_with("fused/autodiff.rs")
            && !f.ends_with("nets/src/gate.rs")
    }));
    let broken = find(
        &files,
        &["backend::autodiff", ".autodiff()", "AutodiffBackend"],
    );
    assert!(broken.is_empty(), "{broken:#?}");
}

#[test]
fn the_gpu_kernels_share_semantics_not_the_cpu_path() {
    let broken = find(
        &rust_files(&workspace().join("crates/splat/src/cube")),
        &["crate::cpu"],
    );
    assert!(broken.is_empty(), "{broken:#?}");
}

/// CubeCL's CUDA runtime allocates Burn's tensors with padded rows ("pitched"); the splat
/// kernels index row-major, so what they write must be allocated contiguous (`f3g_splat::cube`'s
/// module doc). wgpu never pads, so no GPU test in CI sees a pitched allocation; this does.
#[test]
fn the_gpu_kernels_write_only_contiguous_allocations() {
    let broken = find(
        &rust_files(&workspace().join("crates/splat/src/cube")),
        &[
            "empty_device_dtype",
            "empty_device(",
            "empty_device::<",
            "float_empty(",
            "int_empty(",
            "create_tensor(",
        ],
    );
    assert!(broken.is_empty(), "{broken:#?}");
}

#[test]
fn every_file_is_written_atomically_but_the_append_only_logs() {
    let files: Vec<PathBuf> = LAYERS
        .iter()
        .filter(|(k, _)| *k != "io")
        .flat_map(|(k, _)| sources(k))
        .collect();
    let broken: Vec<String> = find(
        &files,
        &[
            "fs::write(",
            "File::create(",
            "OpenOptions::new()",
            "fs::copy(",
        ],
    )
    .into_iter()
    // The append-only logs: the training log (documented in train/mod.rs and ARCHITECTURE.md)
    // and `bench train`'s phase marks, appended to a file the offline CUDA driver appends to.
    .filter(|l| {
        let append_only = [
            "crates/avatar/src/train/mod.rs",
            "crates/cli/src/bench/train.rs",
        ];
        !append_only.iter().any(|f| l.starts_with(f)) || !l.contains("OpenOptions")
    })
    .collect();
    assert!(
        broken.is_empty(),
        "write through f3g_io::write_atomic: {broken:#?}"
    );
}

/// The `[features]` of a crate's manifest (one line each): name → entries.
fn features(krate: &str) -> std::collections::BTreeMap<String, Vec<String>> {
    let text =
        std::fs::read_to_string(workspace().join("crates").join(krate).join("Cargo.toml")).unwrap();
    let mut section = String::new();
    let mut out = std::collections::BTreeMap::new();
    for line in text.lines().map(str::trim) {
        if line.starts_with('[') {
            section = line.to_string();
        } else if section == "[features]"
            && !line.starts_with('#')
            && let Some((name, list)) = line.split_once('=')
        {
            let entries = list
                .trim()
                .trim_start_matches('[')
                .trim_end_matches(']')
                .split(',')
                .map(|e| e.trim().trim_matches('"').to_string())
                .filter(|e| !e.is_empty())
                .collect();
            out.insert(name.trim().to_string(), entries);
        }
    }
    out
}

/// A `cuda` feature builds what it says: kernels compile with NVRTC (cubecl-cuda's `cpp`
/// compiler; the LLVM one is a stub here).
#[test]
fn every_cuda_feature_compiles_with_nvrtc() {
    let root = std::fs::read_to_string(workspace().join("Cargo.toml")).unwrap();
    let entry = root
        .lines()
        .find(|l| l.starts_with("cubecl-cuda "))
        .expect("the workspace names cubecl-cuda");
    assert!(entry.contains("\"cpp\""), "{entry}");
    let mut broken = Vec::new();
    for (krate, _) in LAYERS {
        let Some(own) = features(krate).get("cuda").cloned() else {
            continue;
        };
        if own.iter().any(|e| e == "burn/cuda") && !own.iter().any(|e| e == "dep:cubecl-cuda") {
            broken.push(format!(
                "crates/{krate}: `cuda` turns on burn/cuda without dep:cubecl-cuda"
            ));
        }
    }
    assert!(broken.is_empty(), "{broken:#?}");
}

/// A GPU feature builds what it says: `f3g-cli --features gpu` must turn on the Cube
/// implementations of every crate below it (a crate left out answers a GPU tensor with Burn's
/// `unimplemented!`), and Burn's `fusion` changes the type of every GPU tensor, so a crate fused
/// alone would see another backend than the crates it calls. Each of these features must reach
/// every crate below that has it, through the crates between.
#[test]
fn every_gpu_feature_reaches_every_crate_below_that_has_it() {
    let broken: Vec<String> = ["gpu", "cuda", "autotune", "fusion"]
        .into_iter()
        .flat_map(unreached)
        .collect();
    assert!(broken.is_empty(), "{broken:#?}");
}

/// CI builds the GPU code once, with every GPU feature together (`.ci/run`: a build per
/// feature set costs 20-30 minutes), so the README's own build lines are checked here: each
/// `cargo build -p CRATE --features F,G` names a crate of the workspace and features of its
/// manifest, each of them one whose reach the test above checks.
#[test]
fn the_readmes_build_lines_name_features_that_reach_every_crate_below() {
    let readme = std::fs::read_to_string(workspace().join("README.md")).unwrap();
    let checked = ["gpu", "cuda", "autotune", "fusion"];
    let mut lines = 0;
    let mut broken = Vec::new();
    for line in readme.lines().filter(|l| l.contains("cargo build")) {
        let words: Vec<&str> = line.split_whitespace().collect();
        let after = |flag: &str| {
            words
                .iter()
                .position(|w| *w == flag)
                .and_then(|i| words.get(i + 1).copied())
        };
        let (Some(package), Some(list)) = (after("-p"), after("--features")) else {
            continue;
        };
        lines += 1;
        let krate = package.strip_prefix("f3g-").unwrap_or(package);
        let own = features(krate);
        for feature in list.split(',') {
            if !own.contains_key(feature) {
                broken.push(format!(
                    "README: `{line}`: {package} has no feature `{feature}`"
                ));
            } else if !checked.contains(&feature) {
                broken.push(format!(
                    "README: `{line}`: `{feature}`'s reach is not checked"
                ));
            }
        }
    }
    assert!(lines >= 2, "the README's GPU build lines were not found");
    assert!(broken.is_empty(), "{broken:#?}");
}

/// The offline CUDA source extraction is test code: no crate's feature turns it on, so no
/// `f3g` build carries it.
#[test]
fn only_tests_extract_cuda_sources() {
    let broken: Vec<String> = LAYERS
        .iter()
        .flat_map(|(krate, _)| {
            features(krate)
                .into_iter()
                .filter(|(_, entries)| entries.iter().any(|e| e == "f3g-splat/cuda-source"))
                .map(move |(name, _)| format!("crates/{krate}: `{name}` turns on cuda-source"))
        })
        .collect();
    assert!(broken.is_empty(), "{broken:#?}");
}

/// The crates below `krate` (every workspace crate it depends on, directly or not), without
/// the `f3g-` prefix.
fn crates_below(krate: &str) -> BTreeSet<String> {
    let mut below = BTreeSet::new();
    let mut todo = vec![krate.to_string()];
    while let Some(krate) = todo.pop() {
        for dep in dependencies(&krate) {
            if let Some(dep) = dep.strip_prefix("f3g-")
                && below.insert(dep.to_string())
            {
                todo.push(dep.to_string());
            }
        }
    }
    below
}

/// The crates below a crate with `feature` that have it too but that its `feature` does not
/// turn on (directly or through the same feature of a crate it turns on).
fn unreached(feature: &str) -> Vec<String> {
    let own = |krate: &str| features(krate).get(feature).cloned();
    let suffix = format!("/{feature}");
    let mut broken = Vec::new();
    for (krate, _) in LAYERS {
        let Some(list) = own(krate) else { continue };
        let mut reached = BTreeSet::new();
        let mut todo = vec![list];
        while let Some(list) = todo.pop() {
            for dep in list
                .iter()
                .filter_map(|e| e.strip_prefix("f3g-")?.strip_suffix(suffix.as_str()))
            {
                if reached.insert(dep.to_string()) {
                    todo.extend(own(dep));
                }
            }
        }
        for dep in crates_below(krate) {
            if own(&dep).is_some() && !reached.contains(&dep) {
                broken.push(format!(
                    "crates/{krate}: `{feature}` does not turn on f3g-{dep}/{feature}"
                ));
            }
        }
    }
    broken
}

/// A dependency nothing uses still costs every build its compile time (the npz reader's zip
/// brought two C libraries no `.npz` needs; four crates listed dependencies they no longer
/// used, 2026-12-01). A `[dependencies]` entry must be named in the crate's `src/` outside its
/// test modules (a path `name::…` or a macro `name!`, [`names_crate`]), a `[dev-dependencies]`
/// entry in its `src/` or `tests/`; an optional
/// dependency that one of the crate's features turns on (`dep:name`) may be there only for the
/// features it sets on a dependency shared with other crates.
#[test]
fn every_dependency_a_crate_lists_is_used() {
    let mut unused = Vec::new();
    for (krate, _) in LAYERS {
        let dir = workspace().join("crates").join(krate);
        // The library's code without its test modules; all code, tests included (comment lines
        // left out of both).
        let (mut library, mut everything) = (String::new(), String::new());
        for folder in ["src", "tests"] {
            let path = dir.join(folder);
            if !path.is_dir() {
                continue;
            }
            for file in &rust_files(&path) {
                if folder == "src" {
                    for (_, line) in code_lines(file) {
                        library.push_str(&line);
                        library.push('\n');
                    }
                }
                let text = std::fs::read_to_string(file).unwrap();
                for line in text.lines().filter(|l| !l.trim_start().starts_with("//")) {
                    everything.push_str(line);
                    everything.push('\n');
                }
            }
        }
        let switched_on: BTreeSet<String> = features(krate)
            .into_values()
            .flatten()
            .filter_map(|entry| entry.strip_prefix("dep:").map(str::to_string))
            .collect();
        for (section, code) in [
            ("[dependencies]", &library),
            ("[dev-dependencies]", &everything),
        ] {
            for name in manifest_entries(krate, section) {
                if !names_crate(code, &name.replace('-', "_")) && !switched_on.contains(&name) {
                    unused.push(format!("crates/{krate}/Cargo.toml {section} {name}"));
                }
            }
        }
    }
    assert!(
        unused.is_empty(),
        "dependencies no code of their crate names:\n{}",
        unused.join("\n")
    );
}

/// Whether `code` names the crate `ident` as a path's first segment or a macro's path (`ident::`,
/// `ident!`, not `other_ident::`).
fn names_crate(code: &str, ident: &str) -> bool {
    code.match_indices(ident).any(|(at, _)| {
        let before = code[..at].chars().next_back();
        let after = &code[at + ident.len()..];
        !before.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == ':')
            && (after.starts_with("::") || after.starts_with('!'))
    })
}

#[test]
fn a_crate_is_named_by_its_paths_not_by_a_longer_name() {
    assert!(names_crate("use rand::Rng;", "rand"));
    assert!(names_crate("let x = serde_json!(1);", "serde_json"));
    assert!(!names_crate("use rand_chacha::ChaCha8Rng;", "rand"));
    assert!(!names_crate("use burn::backend::rand::x;", "rand"));
    assert!(!names_crate("fn grand::x", "rand"));
}
