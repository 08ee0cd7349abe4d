#!/usr/bin/env bash
# The vendored burn-cubecl (third_party/burn-cubecl) as the crates.io crate plus one patch.
#
#   tools/burn-patch.sh check   # the vendored tree equals burn-cubecl 0.22.1 + the patch (CI)
#   tools/burn-patch.sh make    # write third_party/burn-cubecl.patch from the vendored tree
#
# The crate comes from crates.io through cargo itself (`cargo fetch` of a throw-away package
# that depends on it), checked against the checksum below: the index's, which every Cargo.lock
# naming burn-cubecl 0.22.1 records. The files cargo adds when it packages a crate
# (`Cargo.lock`, `Cargo.toml.orig`, `.cargo_vcs_info.json`) are not vendored, so not compared.
# What each change does and why: third_party/burn-cubecl.md.
set -euo pipefail
cd "$(dirname "$0")/.."

name=burn-cubecl
version=0.22.1
sha256=8d00b95290d2a8de2529aea94c1106a96c7f433eb314da1bba133c068479e3ce
tree=third_party/$name
patch_file=third_party/$name.patch

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# The published crate, unpacked as $work/a.
published() {
    mkdir -p "$work/fetch/src"
    printf '[package]\nname = "fetch"\nversion = "0.0.0"\nedition = "2024"\n[dependencies]\n%s = { version = "=%s", default-features = false }\n' \
        "$name" "$version" >"$work/fetch/Cargo.toml"
    : >"$work/fetch/src/lib.rs"
    (cd "$work/fetch" && cargo fetch --quiet)
    local crate
    crate=$(ls "${CARGO_HOME:-$HOME/.cargo}"/registry/cache/*/"$name-$version.crate" | head -1)
    echo "$sha256  $crate" | sha256sum --check --quiet
    tar -xzf "$crate" -C "$work"
    mv "$work/$name-$version" "$work/a"
    rm -f "$work/a/Cargo.lock" "$work/a/Cargo.toml.orig" "$work/a/.cargo_vcs_info.json"
}

case "${1:-}" in
make)
    published
    cp -r "$tree" "$work/b"
    # diff exits 1 when the trees differ, as they must.
    (cd "$work" && diff -ruN a b) >"$patch_file" || [ $? = 1 ]
    echo "$patch_file: $(grep -c '^diff ' "$patch_file") files, $(wc -l <"$patch_file") lines"
    ;;
check)
    published
    (cd "$work/a" && patch --quiet -p1 --no-backup-if-mismatch) <"$patch_file"
    if ! diff -r "$work/a" "$tree" >"$work/differences"; then
        cat "$work/differences" >&2
        echo "$tree is not $name $version + $patch_file: change the vendored tree and run" \
            "tools/burn-patch.sh make, or the other way round" >&2
        exit 1
    fi
    echo "$tree = $name $version + $patch_file"
    ;;
*)
    sed -n '2,10p' "$0"
    exit 2
    ;;
esac
