//! Debian packages, installed so that nothing else on the machine changes.
//!
//! - Only **missing** packages are named to apt: naming an installed library would upgrade it (and
//!   with it, say, systemd).
//! - Every install is first **simulated** (`apt-get -s`, which needs no root and changes
//!   nothing): if apt would remove any package to make room, set-up stops and names it with what to
//!   do, rather than remove it. The install itself then runs with `--no-remove` as well, so that a
//!   package list that changed in between cannot make apt remove one either.
//! - **No recommends** (`--no-install-recommends`): Chromium's alone would bring avahi-daemon,
//!   udev, CUPS helpers and the Samba libraries.

use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{bail, Context, Result};

use crate::{on_path, output_of, step_attached};

/// The flags of every `apt-get install` set-up runs.
pub const INSTALL_FLAGS: &[&str] = &["--no-install-recommends", "--no-remove"];

/// Waits for another package manager's lock instead of failing at once.
const LOCK_TIMEOUT: [&str; 2] = ["-o", "DPkg::Lock::Timeout=600"];

/// What `apt-get -s install` says it would do.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct Simulation {
    /// Packages it would install or upgrade.
    pub installs: Vec<String>,
    /// Packages it would remove to make room.
    pub removals: Vec<String>,
}

/// Reads `apt-get -s`'s action lines: `Inst NAME (…)` and `Remv NAME […]`.
pub fn parse_simulation(text: &str) -> Simulation {
    let mut simulation = Simulation::default();
    for line in text.lines() {
        let mut words = line.split_whitespace();
        let list = match words.next() {
            Some("Inst") => &mut simulation.installs,
            Some("Remv") => &mut simulation.removals,
            _ => continue,
        };
        if let Some(name) = words.next() {
            list.push(name.to_owned());
        }
    }
    simulation
}

/// What installing `packages` (without recommends) would do; changes nothing. Run without
/// `--no-remove`, so that apt lists the removals instead of only refusing.
pub fn simulate(packages: &[&str]) -> Result<Simulation> {
    let out = Command::new("apt-get")
        .args(["-s", "install", "--no-install-recommends"])
        .args(packages)
        .env("LC_ALL", "C")
        .output()
        .context("cannot run `apt-get -s` (set-up installs from Debian's packages)")?;
    if !out.status.success() {
        bail!(
            "`apt-get -s install {}` failed: {}",
            packages.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    Ok(parse_simulation(&String::from_utf8_lossy(&out.stdout)))
}

/// Those of `packages` that dpkg does not list as installed.
pub fn missing<'a>(packages: &[&'a str]) -> Vec<&'a str> {
    packages
        .iter()
        .copied()
        .filter(|p| !is_installed(p))
        .collect()
}

/// Whether dpkg lists `package` as installed.
pub fn is_installed(package: &str) -> bool {
    output_of("dpkg-query", &["-W", "-f=${Status}", package])
        .is_some_and(|status| status.contains("install ok installed"))
}

/// The packages `packages` depend on (`Depends` and `Pre-Depends`), without `packages` themselves:
/// the first of each group of alternatives, virtual packages skipped.
pub fn dependencies(packages: &[&str]) -> Result<Vec<String>> {
    let out = output_of(
        "apt-cache",
        &[
            &[
                "depends",
                "--no-recommends",
                "--no-suggests",
                "--no-conflicts",
                "--no-breaks",
                "--no-replaces",
                "--no-enhances",
            ],
            packages,
        ]
        .concat(),
    )
    .with_context(|| format!("`apt-cache depends {}` failed", packages.join(" ")))?;
    Ok(parse_dependencies(&out, packages))
}

/// Reads `apt-cache depends`: `  Depends: NAME`, `  PreDepends: NAME`, and `  |Depends: NAME` for
/// an alternative whose group continues on the next line.
pub fn parse_dependencies(text: &str, exclude: &[&str]) -> Vec<String> {
    let mut found: Vec<String> = Vec::new();
    let mut in_group = false;
    for line in text.lines() {
        let line = line.trim();
        let (alternative, rest) = match line.strip_prefix('|') {
            Some(rest) => (true, rest),
            None => (false, line),
        };
        let Some(name) = rest
            .strip_prefix("Depends:")
            .or_else(|| rest.strip_prefix("PreDepends:"))
            .map(str::trim)
        else {
            continue;
        };
        let first_of_group = !in_group;
        in_group = alternative;
        let virtual_package = name.starts_with('<');
        if first_of_group
            && !virtual_package
            && !exclude.contains(&name)
            && !found.iter().any(|f| f == name)
        {
            found.push(name.to_owned());
        }
    }
    found
}

/// Why set-up refuses: installing `packages` would remove `removals`.
pub fn removal_refusal(what: &str, packages: &[&str], removals: &[String]) -> String {
    let removals = removals.join(" ");
    let packages = packages.join(" ");
    format!(
        "installing {what} ({packages}) through apt would REMOVE {removals}; set-up never removes \
         a package. Either install {packages} yourself in a way that keeps {removals} (for \
         example from the same release or backport as {removals}), or, if nothing on this \
         machine needs {removals}, remove it yourself; then run `cargo xtask setup` again. \
         (`apt-get -s install --no-install-recommends {packages}` shows what apt would do.)"
    )
}

/// Installs those of `packages` that are missing, without recommends and without removing any
/// package: refused, naming the package, where apt would remove one.
pub fn install(packages: &[&str], what: &str) -> Result<()> {
    let missing = missing(packages);
    if missing.is_empty() {
        return Ok(());
    }
    refresh()?;
    let simulation = simulate(&missing)?;
    if !simulation.removals.is_empty() {
        bail!(removal_refusal(what, &missing, &simulation.removals));
    }
    step_attached(
        &format!("install {what} ({})", missing.join(" ")),
        &mut install_command(&missing)?,
    )
}

/// `apt-get install -y` with [`INSTALL_FLAGS`], as root or through sudo.
pub fn install_command(packages: &[&str]) -> Result<Command> {
    let mut cmd = privileged("apt-get", packages)?;
    cmd.args(install_args(packages))
        .env("DEBIAN_FRONTEND", "noninteractive");
    Ok(cmd)
}

/// `apt-get`'s arguments for installing `packages`.
fn install_args<'a>(packages: &[&'a str]) -> Vec<&'a str> {
    [
        &LOCK_TIMEOUT[..],
        &["install", "-y"],
        INSTALL_FLAGS,
        packages,
    ]
    .concat()
}

/// `apt-get update`, once per set-up.
pub fn refresh() -> Result<()> {
    static REFRESHED: AtomicBool = AtomicBool::new(false);
    if REFRESHED.load(Ordering::Relaxed) {
        return Ok(());
    }
    step_attached(
        "refresh the Debian package lists",
        privileged("apt-get", &[])?.args(LOCK_TIMEOUT).arg("update"),
    )?;
    REFRESHED.store(true, Ordering::Relaxed);
    Ok(())
}

/// `program` as root: directly when we are root, else through sudo; refused with the commands to
/// run as root when neither.
fn privileged(program: &str, packages: &[&str]) -> Result<Command> {
    if is_root() {
        Ok(Command::new(program))
    } else if on_path("sudo").is_some() {
        let mut cmd = Command::new("sudo");
        cmd.arg(program);
        Ok(cmd)
    } else {
        bail!(
            "installing needs root; run as root:\n    apt-get update && apt-get install -y {} {}",
            INSTALL_FLAGS.join(" "),
            packages.join(" ")
        )
    }
}

fn is_root() -> bool {
    output_of("id", &["-u"]).is_some_and(|uid| uid.trim() == "0")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `apt-get -s install --no-install-recommends qemu-system-misc` on a Debian 12 machine with
    /// the backported qemu-utils 10 (whose `Breaks: qemu-system-common (<< 1:8.0)`).
    const QEMU_ON_A_BACKPORT_MACHINE: &str = "\
NOTE: This is only a simulation!
Reading package lists...
The following packages will be REMOVED:
  qemu-utils
The following NEW packages will be installed:
  qemu-system-common qemu-system-data qemu-system-misc
0 upgraded, 3 newly installed, 1 to remove and 135 not upgraded.
Remv qemu-utils [1:10.0.2+ds-2+deb13u1~bpo12+1]
Inst qemu-system-common (1:7.2+dfsg-7+deb12u18+b3 Debian:12.15/oldstable [amd64])
Inst qemu-system-data (1:7.2+dfsg-7+deb12u18 Debian:12.15/oldstable [all])
Inst qemu-system-misc (1:7.2+dfsg-7+deb12u18+b3 Debian:12.15/oldstable [amd64])
Conf qemu-system-common (1:7.2+dfsg-7+deb12u18+b3 Debian:12.15/oldstable [amd64])
";

    #[test]
    fn a_simulation_names_what_apt_would_remove() {
        let simulation = parse_simulation(QEMU_ON_A_BACKPORT_MACHINE);
        assert_eq!(simulation.removals, ["qemu-utils"]);
        assert_eq!(
            simulation.installs,
            ["qemu-system-common", "qemu-system-data", "qemu-system-misc"]
        );
        let refusal = removal_refusal("QEMU", &["qemu-system-misc"], &simulation.removals);
        assert!(
            refusal.contains("REMOVE qemu-utils") && refusal.contains("never removes"),
            "{refusal}"
        );
        assert_eq!(
            parse_simulation("0 upgraded, 0 newly installed"),
            Simulation::default()
        );
    }

    #[test]
    fn every_install_keeps_packages_and_skips_recommends() {
        let args = install_args(&["chromium", "chromium-driver"]);
        for flag in ["--no-install-recommends", "--no-remove", "chromium-driver"] {
            assert!(args.contains(&flag), "{flag} missing: {args:?}");
        }
        let install = args.iter().position(|a| *a == "install").unwrap();
        assert!(args[install..].contains(&"--no-remove"), "{args:?}");
    }

    #[test]
    fn dependencies_take_the_first_alternative_and_skip_virtual_and_own_packages() {
        let text = "\
qemu-system-misc
  Depends: libaio1
  |Depends: libasound2
  Depends: libasound2-t64
  Depends: <libvirtual>
  Depends: qemu-system-common
  PreDepends: libc6
qemu-system-common
  Depends: libaio1
  Depends: libfdt1
";
        assert_eq!(
            parse_dependencies(text, &["qemu-system-misc", "qemu-system-common"]),
            ["libaio1", "libasound2", "libc6", "libfdt1"]
        );
    }
}
