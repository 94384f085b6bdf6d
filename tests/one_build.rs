//! One build serves both README commands: `cargo run --release` resolves features without the
//! dev-dependencies, `cargo test --release` with them. Every crate the service builds must get
//! the same features either way, or the test command rebuilds it and everything above it (Rerun
//! and Arrow: ~90 crates, minutes). Cargo.toml switches such features on in the normal
//! dependencies; this test names the crate when a new dev-dependency makes the two differ again.

use std::collections::BTreeSet;
use std::process::Command;

/// `name version features` of every crate in the graph, as `cargo tree` resolves it.
fn resolved(edges: &str) -> BTreeSet<String> {
    let out = Command::new(env!("CARGO"))
        .args([
            "tree", "--edges", edges, "--prefix", "none", "--format", "{p} {f}",
        ])
        .arg("--manifest-path")
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/Cargo.toml"))
        .output()
        .expect("cargo runs");
    assert!(
        out.status.success(),
        "cargo tree --edges {edges} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|line| line.trim_end_matches(" (*)").trim().to_string())
        .filter(|line| !line.is_empty())
        .collect()
}

#[test]
fn the_tests_build_every_shared_crate_with_the_features_of_the_service_build() {
    let service = resolved("normal,build");
    let tests = resolved("normal,build,dev");
    assert!(
        service.len() > 300,
        "cargo tree listed only {} crates: not the service's graph",
        service.len()
    );
    let rebuilt: Vec<&String> = service.difference(&tests).collect();
    let changed: Vec<String> = rebuilt
        .iter()
        .map(|line| {
            let crate_version: String = line.split(' ').take(2).collect::<Vec<_>>().join(" ");
            let with_tests = tests
                .iter()
                .filter(|t| t.starts_with(&format!("{crate_version} ")) || **t == crate_version)
                .cloned()
                .collect::<Vec<_>>()
                .join(" | ");
            format!("  {line}\n    with the dev-dependencies: {with_tests}")
        })
        .collect();
    assert!(
        changed.is_empty(),
        "the dev-dependencies change the features of {} crate(s) the service builds, so \
         `cargo test` would rebuild them; switch those features on in [dependencies] \
         (see the comment there):\n{}",
        changed.len(),
        changed.join("\n")
    );
}
