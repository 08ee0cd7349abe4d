#!/usr/bin/env bash
# The vendored Burn and CubeCL crates (third_party/burn-cubecl, third_party/burn-cubecl-fusion,
# third_party/cubecl-common), each the crates.io crate plus one patch.
#
#   tools/burn-patch.sh check [CRATE]   # each vendored tree equals its crate + its patch (CI)
#   tools/burn-patch.sh make  [CRATE]   # write third_party/CRATE.patch from the vendored tree
#
# CRATE: burn-cubecl, burn-cubecl-fusion or cubecl-common; all three when left out. Each crate
# comes from crates.io through cargo itself (`cargo fetch` of a throw-away package that depends
# on it), checked against the checksum below: the index's, which every Cargo.lock naming that
# version records. The files cargo adds when it packages a crate (`Cargo.lock`, `Cargo.toml.orig`,
# `.cargo_vcs_info.json`) are not vendored, so not compared. What each change does and why:
# third_party/CRATE.md.
set -euo pipefail
cd "$(dirname "$0")/.."

declare -A version=(
    [burn-cubecl]=0.22.1
    [burn-cubecl-fusion]=0.22.1
    [cubecl-common]=0.11.3
)
declare -A sha256=(
    [burn-cubecl]=8d00b95290d2a8de2529aea94c1106a96c7f433eb314da1bba133c068479e3ce
    [burn-cubecl-fusion]=cc9bd97d88c053b3c4d62159b21681f6d67018fe1b63d48317cc15e8b349925d
    [cubecl-common]=0d0cf12d9bd1ba40cae471d3963f42c50c2c8df699b04ab83a7c2cbb8923800e
)

mode=${1:-}
crates=${2:-burn-cubecl burn-cubecl-fusion cubecl-common}

# The published crate $1, unpacked as $2.
published() {
    local name=$1 into=$2 work
    local release=${version[$name]}
    work=$(mktemp -d)
    mkdir -p "$work/fetch/src"
    printf '[package]\nname = "fetch"\nversion = "0.0.0"\nedition = "2024"\n[dependencies]\n%s = { version = "=%s", default-features = false }\n' \
        "$name" "$release" >"$work/fetch/Cargo.toml"
    : >"$work/fetch/src/lib.rs"
    (cd "$work/fetch" && cargo fetch --quiet)
    local crate
    crate=$(ls "${CARGO_HOME:-$HOME/.cargo}"/registry/cache/*/"$name-$release.crate" | head -1)
    echo "${sha256[$name]}  $crate" | sha256sum --check --quiet
    tar -xzf "$crate" -C "$work"
    mv "$work/$name-$release" "$into"
    rm -rf "$work"
    rm -f "$into/Cargo.lock" "$into/Cargo.toml.orig" "$into/.cargo_vcs_info.json"
}

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
for name in $crates; do
    [ -n "${sha256[$name]:-}" ] || { sed -n '2,13p' "$0"; exit 2; }
    tree=third_party/$name
    patch_file=third_party/$name.patch
    rm -rf "$work/a" "$work/b"
    case "$mode" in
    make)
        published "$name" "$work/a"
        cp -r "$tree" "$work/b"
        # diff exits 1 when the trees differ, as they must.
        (cd "$work" && diff -ruN a b) >"$patch_file" || [ $? = 1 ]
        echo "$patch_file: $(grep -c '^diff ' "$patch_file") files, $(wc -l <"$patch_file") lines"
        ;;
    check)
        published "$name" "$work/a"
        (cd "$work/a" && patch --quiet -p1 --no-backup-if-mismatch) <"$patch_file"
        if ! diff -r "$work/a" "$tree" >"$work/differences"; then
            cat "$work/differences" >&2
            echo "$tree is not $name ${version[$name]} + $patch_file: change the vendored tree" \
                "and run tools/burn-patch.sh make $name, or the other way round" >&2
            exit 1
        fi
        echo "$tree = $name ${version[$name]} + $patch_file"
        ;;
    *)
        sed -n '2,13p' "$0"
        exit 2
        ;;
    esac
done
