//! Project tasks. The two commands of the README:
//!
//! * `cargo xtask run`  — install what is missing, build the dashboard with
//!   Trunk, start the server on the embedded simulator and print its URL.
//! * `cargo xtask test` — install what is missing, then run every check and
//!   test: formatting, clippy, native tests (incl. server and browser
//!   end-to-end tests), the Python package's tests (pytest, in a virtual
//!   environment under `~/.cache/spintune/venv`) and the wasm tests in
//!   headless Chromium.
//! * `cargo xtask wheel` — the Python package as an abi3 manylinux2014 wheel
//!   (maturin with the zig linker of the `ziglang` pip package), the wheel
//!   the Python tests install into a venv without Rust on the PATH.
//!
//! Every install step is skipped when the right version is already present
//! (binaryen's `wasm-opt`, which Trunk runs on the dashboard, comes from npm
//! into `~/.cache/spintune/node`).
//! Builds go to `$CARGO_TARGET_DIR` (default `~/.cache/spintune/target`, outside
//! the clone, so repeated runs stay warm).

mod deps;

use std::env;
use std::path::{Path, PathBuf};
use std::process::{exit, Command};
use std::time::Instant;

const TRUNK_VERSION: &str = "0.21.14";
const WASM_TARGET: &str = "wasm32-unknown-unknown";
/// binaryen release whose `wasm-opt` Trunk runs on the dashboard (npm
/// package `binaryen`; must match `[tools] wasm_opt` in Trunk.toml). Debian's
/// binaryen (v108) breaks the module in Chromium.
const BINARYEN_VERSION: &str = "132";

fn main() {
    let args: Vec<String> = env::args().skip(1).collect();
    let root = workspace_root();
    env::set_current_dir(&root).expect("cd to workspace root");
    let target_dir = target_dir();
    // Child cargo/trunk processes share this target directory.
    env::set_var("CARGO_TARGET_DIR", &target_dir);
    env::set_var("TRUNK_SKIP_VERSION_CHECK", "true");
    // The runner's timeout covers a whole test binary; cold runs on 2 cores need more than 20 s.
    if env::var_os("WASM_BINDGEN_TEST_TIMEOUT").is_none() {
        env::set_var("WASM_BINDGEN_TEST_TIMEOUT", "180");
    }
    prepend_path(&cargo_bin_dir());
    // npm's binaryen (wasm-opt) before any system one.
    prepend_path(&node_dir().join("node_modules/.bin"));
    match args.first().map(String::as_str) {
        Some("run") => run(&args[1..]),
        Some("test") => test(&args[1..]),
        Some("deps") => {
            if !check_deps(&root) {
                exit(1);
            }
        }
        Some("install") => {
            install_tools(true);
        }
        Some("wheel") => {
            let wheel = build_wheel(&python_env());
            println!("{}", wheel.display());
        }
        Some("python-test") => {
            // The Python step of `test` alone (it needs the debug server
            // binary for its bit-identity tests: built unless SPINTUNE_BIN is set).
            if env::var_os("SPINTUNE_BIN").is_none() {
                cmd("cargo", &["build", "-p", "spintune-server"]);
                env::set_var("SPINTUNE_BIN", target_dir.join("debug/spintune"));
            }
            python_tests();
        }
        _ => {
            eprintln!(
                "usage: cargo xtask <command>\n\n  run [server args]  build the dashboard and start the server on the simulator\n  test [--no-lint]   run formatting/lint checks and every test (native, browser, Python, wasm)\n  deps               list module import cycles (fails if there is one)\n  install            install the tools only (wasm target, trunk, wasm-bindgen, binaryen wasm-opt, chromium)\n  python-test        only the Python package step of `test` (wheel, clean venv without Rust, pytest)\n  wheel              build the abi3 manylinux2014 wheel (maturin + zig) into $CARGO_TARGET_DIR/wheels/spintune"
            );
            exit(2);
        }
    }
}

fn run(server_args: &[String]) {
    install_tools(false);
    build_dashboard();
    step("start the server (Ctrl-C to stop)");
    let mut args: Vec<String> = [
        "run",
        "--release",
        "-p",
        "spintune-server",
        "--",
        "serve",
        "--dist",
        "dist",
    ]
    .map(String::from)
    .to_vec();
    args.extend(server_args.iter().cloned());
    cmd("cargo", &args);
}

/// Print every file-level import cycle of the crates; `true` when there is none.
fn check_deps(root: &Path) -> bool {
    let found = deps::cycles(root, &deps::CRATE_SOURCES);
    for c in &found {
        let files: Vec<String> = c.iter().map(|f| f.display().to_string()).collect();
        println!("cycle: {}", files.join(" → "));
    }
    println!("{} import cycles", found.len());
    found.is_empty()
}

fn test(flags: &[String]) {
    let started = Instant::now();
    let lint = !flags.iter().any(|f| f == "--no-lint");
    install_tools(true);
    if lint {
        step("formatting");
        cmd("cargo", &["fmt", "--all", "--", "--check"]);
        step("module import cycles (cargo xtask deps)");
        if !check_deps(&env::current_dir().unwrap()) {
            eprintln!("xtask: module import cycles (see ARCHITECTURE.md, dependency rules)");
            exit(1);
        }
        step("clippy (native)");
        cmd(
            "cargo",
            &[
                "clippy",
                "--workspace",
                "--all-targets",
                "--",
                "-D",
                "warnings",
            ],
        );
        step("clippy (wasm dashboard)");
        cmd(
            "cargo",
            &[
                "clippy",
                "-p",
                "spintune-web",
                "--target",
                WASM_TARGET,
                "--",
                "-D",
                "warnings",
            ],
        );
    }
    build_dashboard();
    step("build the server binary for the end-to-end tests");
    cmd("cargo", &["build", "-p", "spintune-server"]);
    let bin = PathBuf::from(env::var("CARGO_TARGET_DIR").unwrap()).join("debug/spintune");
    env::set_var("SPINTUNE_BIN", &bin);
    env::set_var("SPINTUNE_DIST", env::current_dir().unwrap().join("dist"));
    step("Python test environment");
    python_env();
    step("native tests (core, server, end-to-end incl. headless Chromium)");
    cmd("cargo", &["test", "--workspace"]);
    python_tests();
    step("wasm tests in headless Chromium (core + dashboard)");
    cmd(
        "cargo",
        &[
            "test",
            "--target",
            WASM_TARGET,
            "-p",
            "spintune",
            "--test",
            "wasm",
        ],
    );
    cmd(
        "cargo",
        &[
            "test",
            "--target",
            WASM_TARGET,
            "-p",
            "spintune-web",
            "--lib",
            "--bins",
            "--tests",
        ],
    );
    eprintln!(
        "\nxtask test: all steps passed in {:.0} s",
        started.elapsed().as_secs_f64()
    );
}

/// Python packages of the build/tool environment (`~/.cache/spintune/venv`):
/// (import name, pip name). `websockets` for the lab-bridge client that the
/// native tests run (`SPINTUNE_PYTHON`); maturin and ziglang (its zig
/// linker) build the wheel.
const PYTHON_DEPS: [(&str, &str); 9] = [
    ("websockets", "websockets"),
    ("maturin", "maturin"),
    ("ziglang", "ziglang"),
    ("pytest", "pytest"),
    ("numpy", "numpy"),
    ("xarray", "xarray"),
    ("netCDF4", "netcdf4"),
    ("qcodes", "qcodes"),
    ("tqdm", "tqdm"),
];

/// What the Python tests import, installed into the wheel's test venv
/// (`~/.cache/spintune/venv-wheel`): (import name, pip name).
const WHEEL_TEST_DEPS: [(&str, &str); 9] = [
    ("pytest", "pytest"),
    ("numpy", "numpy"),
    ("xarray", "xarray"),
    ("netCDF4", "netcdf4"),
    ("qcodes", "qcodes"),
    ("qcodes_contrib_drivers", "qcodes_contrib_drivers"),
    ("pyvisa_sim", "pyvisa-sim"),
    ("tqdm", "tqdm"),
    ("websockets", "websockets"),
];

/// A virtual environment at `venv` (created if missing) with `deps`
/// (installed only if their import fails). `path`: the PATH pip runs with.
fn ensure_venv(venv: &Path, deps: &[(&str, &str)], path: Option<&std::ffi::OsStr>) {
    let python = venv.join("bin/python");
    if python.is_file() {
        eprintln!("  venv {}: present", venv.display());
    } else {
        if output("python3", &["--version"]).is_none() {
            eprintln!("xtask: python3 was not found on PATH; the Python tests need it");
            exit(1);
        }
        std::fs::create_dir_all(venv.parent().unwrap_or(Path::new("."))).expect("cache dir");
        cmd("python3", &["-m", "venv", &venv.to_string_lossy()]);
    }
    let python = python.to_string_lossy().into_owned();
    let missing: Vec<&str> = deps
        .iter()
        .filter(|(module, _)| {
            !Command::new(&python)
                .args(["-c", &format!("import {module}")])
                .stdout(std::process::Stdio::null())
                .stderr(std::process::Stdio::null())
                .status()
                .is_ok_and(|s| s.success())
        })
        .map(|(_, pip)| *pip)
        .collect();
    if missing.is_empty() {
        eprintln!("  Python packages: present");
    } else {
        let mut args = vec![
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
        ];
        args.extend(&missing);
        run_python(&python, &args, venv, path);
    }
}

/// Run `python args…` with `VIRTUAL_ENV=venv` and (if given) that PATH; exit on failure.
fn run_python(python: &str, args: &[&str], venv: &Path, path: Option<&std::ffi::OsStr>) {
    eprintln!("  $ {python} {}", args.join(" "));
    let mut c = Command::new(python);
    c.args(args).env("VIRTUAL_ENV", venv);
    if let Some(path) = path {
        c.env("PATH", path);
    }
    match c.status() {
        Ok(s) if s.success() => {}
        Ok(s) => {
            eprintln!("xtask: `python {}` failed ({s})", args.join(" "));
            exit(s.code().unwrap_or(1));
        }
        Err(e) => {
            eprintln!("xtask: could not start {python}: {e}");
            exit(1);
        }
    }
}

/// The build/tool environment of the Python steps: a virtual environment
/// outside the clone (`$SPINTUNE_VENV`, default `~/.cache/spintune/venv`)
/// with [`PYTHON_DEPS`], installed only if missing. Exported as
/// `SPINTUNE_PYTHON` (the interpreter) for the native tests that run Python
/// (the lab bridge client); nothing is installed inside a test. Returns the
/// venv directory.
fn python_env() -> PathBuf {
    let venv = env::var_os("SPINTUNE_VENV")
        .map(PathBuf::from)
        .unwrap_or_else(|| home().join(".cache/spintune/venv"));
    ensure_venv(&venv, &PYTHON_DEPS, None);
    env::set_var("SPINTUNE_PYTHON", venv.join("bin/python"));
    venv
}

/// Every file under `dirs` (recursively), sorted.
fn files_under(dirs: &[&Path]) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack: Vec<PathBuf> = dirs.iter().map(|d| d.to_path_buf()).collect();
    while let Some(p) = stack.pop() {
        if p.is_dir() {
            if let Ok(rd) = std::fs::read_dir(&p) {
                for e in rd.flatten() {
                    let name = e.file_name();
                    let name = name.to_string_lossy();
                    if name == "__pycache__" || name == "target" || name.starts_with('.') {
                        continue;
                    }
                    stack.push(e.path());
                }
            }
        } else {
            out.push(p);
        }
    }
    out.sort();
    out
}

/// A fingerprint of what the wheel is built from (the Python package, the
/// core, the workspace manifests and lock file): the wheel is rebuilt only
/// when it changes.
fn wheel_inputs_fingerprint(root: &Path) -> String {
    use std::hash::{Hash, Hasher};
    let mut h = std::collections::hash_map::DefaultHasher::new();
    let mut files = files_under(&[
        &root.join("python/src"),
        &root.join("python/pysrc"),
        &root.join("shared"),
    ]);
    files.extend(
        [
            "python/Cargo.toml",
            "python/pyproject.toml",
            "python/README.md",
            "Cargo.toml",
            "Cargo.lock",
        ]
        .iter()
        .map(|f| root.join(f)),
    );
    for f in files {
        f.strip_prefix(root).unwrap_or(&f).hash(&mut h);
        std::fs::read(&f).unwrap_or_default().hash(&mut h);
    }
    format!("{:016x}", h.finish())
}

/// Build the wheel (abi3, manylinux2014, linked with zig from the `ziglang`
/// package) into `$CARGO_TARGET_DIR/wheels/spintune` and return its path.
/// Cached: the build is skipped when the wheel's inputs have not changed
/// since the last build (and cargo's release build in the target dir is
/// incremental anyway).
fn build_wheel(venv: &Path) -> PathBuf {
    step("Python wheel (maturin, abi3, manylinux2014, zig linker)");
    let root = env::current_dir().expect("cwd");
    let out =
        PathBuf::from(env::var("CARGO_TARGET_DIR").expect("set in main")).join("wheels/spintune");
    let stamp = out.join("inputs.fingerprint");
    let fingerprint = wheel_inputs_fingerprint(&root);
    let find_wheel = || -> Option<PathBuf> {
        std::fs::read_dir(&out)
            .ok()?
            .flatten()
            .map(|e| e.path())
            .find(|p| p.extension().is_some_and(|e| e == "whl"))
    };
    if std::fs::read_to_string(&stamp).ok().as_deref() == Some(fingerprint.as_str()) {
        if let Some(w) = find_wheel() {
            eprintln!("  {}: up to date", w.display());
            return w;
        }
    }
    let _ = std::fs::remove_dir_all(&out);
    std::fs::create_dir_all(&out).expect("wheel dir");
    let python = venv.join("bin/python").to_string_lossy().into_owned();
    // maturin finds `python -m ziglang` through the interpreter it runs on.
    let path = env::join_paths(
        std::iter::once(venv.join("bin"))
            .chain(env::split_paths(&env::var_os("PATH").unwrap_or_default())),
    )
    .expect("valid PATH");
    run_python(
        &python,
        &[
            "-m",
            "maturin",
            "build",
            "--release",
            "--zig",
            "--compatibility",
            "manylinux2014",
            "-m",
            "python/Cargo.toml",
            "--out",
            &out.to_string_lossy(),
        ],
        venv,
        Some(&path),
    );
    let wheel = find_wheel().unwrap_or_else(|| {
        eprintln!("xtask: maturin wrote no wheel into {}", out.display());
        exit(1);
    });
    std::fs::write(&stamp, &fingerprint).expect("write the wheel's fingerprint");
    wheel
}

/// PATH without Rust: every entry that holds `cargo`, `rustc` or `rustup`
/// is dropped (e.g. `~/.cargo/bin`), so the tests show that the wheel
/// needs no Rust toolchain.
fn path_without_rust() -> std::ffi::OsString {
    let keep: Vec<PathBuf> = env::split_paths(&env::var_os("PATH").unwrap_or_default())
        .filter(|d| {
            !["cargo", "rustc", "rustup"]
                .iter()
                .any(|t| d.join(t).exists())
        })
        .collect();
    env::join_paths(keep).expect("valid PATH")
}

/// The Python package step: build the wheel ([`build_wheel`]), install it
/// into a venv of its own (`$SPINTUNE_WHEEL_VENV`, default
/// `~/.cache/spintune/venv-wheel`, created once, test dependencies
/// installed only if missing) and run pytest there — pip and pytest with no
/// Rust on the PATH.
fn python_tests() {
    step("Python package (wheel into a venv without Rust on the PATH, then pytest)");
    let started = Instant::now();
    let build_venv = python_env();
    let wheel = build_wheel(&build_venv);
    let venv = env::var_os("SPINTUNE_WHEEL_VENV")
        .map(PathBuf::from)
        .unwrap_or_else(|| home().join(".cache/spintune/venv-wheel"));
    let path = path_without_rust();
    ensure_venv(&venv, &WHEEL_TEST_DEPS, Some(&path));
    let python = venv.join("bin/python").to_string_lossy().into_owned();
    // The venv's bin first (so `python` in a test's subprocess is this one).
    let path = env::join_paths(std::iter::once(venv.join("bin")).chain(env::split_paths(&path)))
        .expect("valid PATH");
    run_python(
        &python,
        &[
            "-c",
            "import shutil, sys\nfound = [t for t in ('cargo', 'rustc', 'rustup') if shutil.which(t)]\nsys.exit(f'Rust on the PATH of the wheel tests: {found}' if found else 0)",
        ],
        &venv,
        Some(&path),
    );
    run_python(
        &python,
        &[
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
            "--no-deps",
            "--force-reinstall",
            &wheel.to_string_lossy(),
        ],
        &venv,
        Some(&path),
    );
    run_python(
        &python,
        &["-m", "pytest", "python/tests", "-q"],
        &venv,
        Some(&path),
    );
    eprintln!(
        "  Python package step: {:.0} s",
        started.elapsed().as_secs_f64()
    );
}

fn build_dashboard() {
    step("build the dashboard (trunk, release)");
    cmd("trunk", &["build", "--release", "--offline"]);
}

/// Install what is missing; `browser` also installs Chromium + ChromeDriver.
fn install_tools(browser: bool) {
    step("toolchain check");
    let installed = output("rustup", &["target", "list", "--installed"]).unwrap_or_default();
    if !installed.lines().any(|l| l.trim() == WASM_TARGET) {
        cmd("rustup", &["target", "add", WASM_TARGET]);
    } else {
        eprintln!("  wasm32 target: present");
    }
    let wb = wasm_bindgen_version();
    let have_wb = output("wasm-bindgen", &["--version"]).unwrap_or_default();
    let have_runner = output("wasm-bindgen-test-runner", &["--version"]).unwrap_or_default();
    if have_wb.contains(&wb) && have_runner.contains(&wb) {
        eprintln!("  wasm-bindgen-cli {wb}: present");
    } else {
        // Without --locked: its lockfile names a crate version the registry mirror lacks.
        cmd(
            "cargo",
            &["install", "wasm-bindgen-cli", "--version", &wb, "--force"],
        );
    }
    if output("trunk", &["--version"])
        .unwrap_or_default()
        .contains(TRUNK_VERSION)
    {
        eprintln!("  trunk {TRUNK_VERSION}: present");
    } else {
        cmd(
            "cargo",
            &["install", "--locked", "trunk", "--version", TRUNK_VERSION],
        );
    }
    if output("wasm-opt", &["--version"])
        .unwrap_or_default()
        .contains(&format!("version_{BINARYEN_VERSION}"))
    {
        eprintln!("  wasm-opt (binaryen {BINARYEN_VERSION}): present");
    } else {
        let prefix = node_dir();
        cmd(
            "npm",
            &[
                "install",
                "--no-save",
                "--prefix",
                &prefix.to_string_lossy(),
                &format!("binaryen@{BINARYEN_VERSION}"),
            ],
        );
    }
    if browser {
        if which("chromium") && which("chromedriver") {
            eprintln!("  chromium + chromedriver: present");
        } else {
            let sudo = if is_root() { vec![] } else { vec!["sudo"] };
            let apt = |args: &[&str]| {
                let mut full: Vec<&str> = sudo.clone();
                full.push("apt-get");
                full.extend_from_slice(args);
                cmd(full[0], &full[1..]);
            };
            apt(&["update", "-qq"]);
            apt(&["install", "-y", "-qq", "chromium", "chromium-driver"]);
        }
    }
}

/// The wasm-bindgen version pinned in Cargo.lock.
fn wasm_bindgen_version() -> String {
    let lock = std::fs::read_to_string("Cargo.lock").expect("Cargo.lock is committed");
    let mut lines = lock.lines();
    while let Some(l) = lines.next() {
        if l.trim() == "name = \"wasm-bindgen\"" {
            if let Some(v) = lines
                .next()
                .and_then(|v| v.trim().strip_prefix("version = \""))
            {
                return v.trim_end_matches('"').to_string();
            }
        }
    }
    eprintln!("xtask: wasm-bindgen not found in Cargo.lock");
    exit(1);
}

/// The checkout this xtask was run from. `cargo run` sets
/// `CARGO_MANIFEST_DIR` for the process; the compile-time value is only the
/// fallback: with a `CARGO_TARGET_DIR` shared by several checkouts, cargo
/// reuses one xtask binary for all of them (its fingerprint does not
/// include the checkout's path), so a path baked in at compile time would
/// send a run in one checkout to the sources of another.
fn workspace_root() -> PathBuf {
    let manifest_dir = env::var_os("CARGO_MANIFEST_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")));
    manifest_dir
        .parent()
        .expect("xtask lives in the workspace")
        .to_path_buf()
}

fn home() -> PathBuf {
    env::var_os("HOME")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/tmp"))
}

fn target_dir() -> PathBuf {
    env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| home().join(".cache/spintune/target"))
}

/// Where npm installs binaryen (`node_modules/.bin/wasm-opt`), outside the clone.
fn node_dir() -> PathBuf {
    home().join(".cache/spintune/node")
}

fn cargo_bin_dir() -> PathBuf {
    env::var_os("CARGO_HOME")
        .map(PathBuf::from)
        .unwrap_or_else(|| home().join(".cargo"))
        .join("bin")
}

fn prepend_path(dir: &Path) {
    let path = env::var_os("PATH").unwrap_or_default();
    let mut parts: Vec<PathBuf> = vec![dir.to_path_buf()];
    parts.extend(env::split_paths(&path));
    env::set_var("PATH", env::join_paths(parts).expect("valid PATH"));
}

fn is_root() -> bool {
    output("id", &["-u"]).is_some_and(|s| s.trim() == "0")
}

fn which(tool: &str) -> bool {
    env::var_os("PATH")
        .map(|p| env::split_paths(&p).any(|d| d.join(tool).is_file()))
        .unwrap_or(false)
}

fn step(what: &str) {
    eprintln!("\n==> {what}");
}

fn output(program: &str, args: &[&str]) -> Option<String> {
    let out = Command::new(program).args(args).output().ok()?;
    out.status.success().then(|| {
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr)
    })
}

fn cmd<S: AsRef<str>>(program: &str, args: &[S]) {
    let args: Vec<&str> = args.iter().map(AsRef::as_ref).collect();
    eprintln!("  $ {program} {}", args.join(" "));
    match Command::new(program).args(&args).status() {
        Ok(s) if s.success() => {}
        Ok(s) => {
            eprintln!("xtask: `{program} {}` failed ({s})", args.join(" "));
            exit(s.code().unwrap_or(1));
        }
        Err(e) => {
            eprintln!("xtask: could not start `{program}`: {e}");
            exit(1);
        }
    }
}
