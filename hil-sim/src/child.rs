//! Child processes that never outlive the process that started them.
//!
//! Every process hil-sim starts (QEMU, the LiteX simulator, socat), and those the tests start
//! (`deform` servers, Chromium, `litex_term`), goes through [`spawn`]. On Linux it asks the
//! kernel, with `PR_SET_PDEATHSIG`, to SIGKILL the child when its parent dies, however the parent
//! dies: a return from `main` without dropping it, a SIGTERM or SIGINT with the default action, a
//! failed allocation's abort, even a SIGKILL. A `Drop` that kills the child covers only the first
//! of these; a signal handler covers none of the last three.
//!
//! The kernel sends that signal when the *thread* that forked the child ends, not the process. A
//! child forked by a test's thread or a server's worker thread would be killed when that thread
//! returns, while its owner may still hold it. So every child is forked by one spawner thread
//! that lives as long as the process (started on first use): for the child, its parent's death is
//! then the process's.

use std::io;
use std::process::{Child, Command};
use std::sync::{mpsc, Mutex, OnceLock};
use std::thread;

/// A command to fork and where to send the result.
type Request = (Command, mpsc::Sender<io::Result<Child>>);

/// Starts `cmd` as a child that is SIGKILLed when this process dies (see the module's doc).
pub fn spawn(mut cmd: Command) -> io::Result<Child> {
    die_with_parent(&mut cmd, libc::SIGKILL);
    fork_on_spawner(cmd)
}

/// The shell script of [`tree`]: `cmd` in the background, and on SIGTERM every process of the
/// session killed (`pkill -s 0`: procps, priority "important" in Debian; failing that, the shell's
/// own process group).
const TREE_SCRIPT: &str = r#"trap 'pkill -KILL -s 0 || kill -KILL 0' TERM; "$@" & wait $!"#;

/// `cmd` (its program, arguments, environment and folder) as a process tree that dies with this
/// process, for [`spawn_tree`]; set its stdio, then spawn it there.
///
/// Why: `PR_SET_PDEATHSIG` reaches only the direct child. A `make` killed by it leaves its
/// compilers running (43 of them once, for a LiteX simulator). So the child is a shell that
/// leads a session of its own, runs `cmd` in the background and waits; the kernel sends it
/// SIGTERM when this process dies, and its trap SIGKILLs the whole session: `make`, its shells,
/// the compilers and itself. A session, not a process group: ninja (the BIOS's build) puts each
/// compiler in a process group of its own. Its exit status is `cmd`'s.
pub fn tree(cmd: &Command) -> Command {
    use std::os::unix::process::CommandExt;
    let mut sh = Command::new("sh");
    sh.args(["-c", TREE_SCRIPT, "sh"])
        .arg(cmd.get_program())
        .args(cmd.get_args());
    // SAFETY: setsid is async-signal-safe and allocates nothing. The forked child is no group
    // leader, so it cannot fail with EPERM.
    unsafe {
        sh.pre_exec(|| {
            if libc::setsid() < 0 {
                return Err(io::Error::last_os_error());
            }
            Ok(())
        });
    }
    for (key, value) in cmd.get_envs() {
        match value {
            Some(value) => sh.env(key, value),
            None => sh.env_remove(key),
        };
    }
    if let Some(dir) = cmd.get_current_dir() {
        sh.current_dir(dir);
    }
    sh
}

/// Starts a [`tree`]: its shell gets SIGTERM when this process dies, and kills its group.
pub fn spawn_tree(mut tree: Command) -> io::Result<Child> {
    die_with_parent(&mut tree, libc::SIGTERM);
    fork_on_spawner(tree)
}

/// Forks `cmd` on the one spawner thread (see the module's doc for why).
fn fork_on_spawner(cmd: Command) -> io::Result<Child> {
    static SPAWNER: OnceLock<Mutex<mpsc::Sender<Request>>> = OnceLock::new();
    let spawner = SPAWNER.get_or_init(|| {
        let (tx, rx) = mpsc::channel::<Request>();
        thread::Builder::new()
            .name("hil-sim-spawner".into())
            .spawn(move || {
                for (mut cmd, reply) in rx {
                    let _ = reply.send(cmd.spawn());
                }
            })
            .expect("starting the spawner thread");
        Mutex::new(tx)
    });
    let (reply_tx, reply_rx) = mpsc::channel();
    let sent = spawner
        .lock()
        .map_err(|_| io::Error::other("the spawner thread's lock is poisoned"))?
        .send((cmd, reply_tx));
    if sent.is_err() {
        return Err(io::Error::other("the spawner thread has ended"));
    }
    reply_rx
        .recv()
        .map_err(|_| io::Error::other("the spawner thread has ended"))?
}

/// Sets `PR_SET_PDEATHSIG` to `signal` in the forked child before it runs the program.
#[cfg(target_os = "linux")]
fn die_with_parent(cmd: &mut Command, signal: i32) {
    use std::os::unix::process::CommandExt;
    let parent = std::process::id() as libc::pid_t;
    // SAFETY: the closure runs between fork and exec and calls only async-signal-safe functions
    // (prctl, getppid) and allocates nothing.
    unsafe {
        cmd.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, signal) != 0 {
                return Err(io::Error::last_os_error());
            }
            // The parent may have died before the prctl: then no signal comes, so stop here.
            if libc::getppid() != parent {
                return Err(io::Error::from_raw_os_error(libc::ESRCH));
            }
            Ok(())
        });
    }
}

/// Elsewhere there is no such kernel service: the owners' `Drop` is all there is.
#[cfg(not(target_os = "linux"))]
fn die_with_parent(_cmd: &mut Command, _signal: i32) {}

/// A process as `/proc/PID/stat` shows it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ProcessInfo {
    pub pid: u32,
    pub parent: u32,
    /// The executable's name, as the kernel keeps it (at most 15 bytes: `qemu-system-ris`).
    pub name: String,
    /// `R`, `S`, `D`, … or `Z` for a zombie (dead, not yet reaped).
    pub state: char,
}

/// Reads `/proc/PID/stat`; `None` if there is no such process.
pub fn process_info(pid: u32) -> Option<ProcessInfo> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // `PID (NAME) STATE PPID …`, where NAME may hold spaces and parentheses.
    let (head, tail) = stat.rsplit_once(')')?;
    let name = head.split_once('(')?.1.to_owned();
    let mut fields = tail.split_whitespace();
    let state = fields.next()?.chars().next()?;
    let parent = fields.next()?.parse().ok()?;
    Some(ProcessInfo {
        pid,
        parent,
        name,
        state,
    })
}

/// Whether `pid` runs: exists and is no zombie (a zombie is dead, only not yet reaped by whoever
/// inherited it).
pub fn is_running(pid: u32) -> bool {
    process_info(pid).is_some_and(|p| p.state != 'Z' && p.state != 'X')
}

/// The processes whose parent is `pid`, for tests that check nothing is left behind.
pub fn children_of(pid: u32) -> Vec<ProcessInfo> {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    entries
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter_map(process_info)
        .filter(|p| p.parent == pid)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    /// A child started from a short-lived thread still runs after that thread ended (the
    /// spawner thread forked it), and is killed once its parent process dies.
    #[test]
    fn a_child_outlives_the_thread_that_asked_for_it() {
        let mut child = thread::spawn(|| {
            let mut cmd = Command::new("sleep");
            cmd.arg("30");
            spawn(cmd).unwrap()
        })
        .join()
        .unwrap();
        thread::sleep(Duration::from_millis(200));
        assert!(
            child.try_wait().unwrap().is_none(),
            "the child died with the thread that asked for it"
        );
        child.kill().unwrap();
        child.wait().unwrap();
    }

    /// A parent killed by SIGKILL (no destructor, no handler runs) takes its child along. The
    /// parent is a copy of this test binary running the ignored helper below.
    #[test]
    fn a_child_dies_when_its_parent_is_killed() {
        let (mut parent, pid_file) = start_helper("helper_parent_that_spawns_sleep");
        let sleeper = sleep_started_by(&pid_file);
        assert_eq!(process_info(sleeper).unwrap().parent, parent.id());
        kill_and_see_it_die(&mut parent, sleeper);
        let _ = std::fs::remove_file(&pid_file);
    }

    /// A tree's exit status, environment and folder are its command's.
    #[test]
    fn a_tree_runs_its_command_as_given() {
        let dir = std::env::temp_dir();
        let mut cmd = Command::new("sh");
        cmd.args([
            "-c",
            "test \"$PWD\" = \"$1\" && test \"$TREE_VAR\" = set && exit 3",
            "sh",
        ])
        .arg(&dir)
        .env("TREE_VAR", "set")
        .current_dir(&dir);
        let status = spawn_tree(tree(&cmd)).unwrap().wait().unwrap();
        assert_eq!(status.code(), Some(3));
        let status = spawn_tree(tree(Command::new("false").env("TREE_VAR", "x")))
            .unwrap()
            .wait()
            .unwrap();
        assert_eq!(status.code(), Some(1));
    }

    /// A tree's grandchild (a compiler under `make`) dies when the tree's parent is SIGKILLed,
    /// even in a process group of its own (as ninja puts its compilers).
    #[test]
    fn a_trees_grandchild_dies_when_its_parent_is_killed() {
        let (mut parent, pid_file) = start_helper("helper_parent_that_spawns_a_tree");
        let sleeper = sleep_started_by(&pid_file);
        assert_ne!(process_info(sleeper).unwrap().parent, parent.id());
        assert_eq!(
            process_group(sleeper),
            Some(sleeper),
            "sleep leads no group of its own"
        );
        kill_and_see_it_die(&mut parent, sleeper);
        let _ = std::fs::remove_file(&pid_file);
    }

    /// A copy of this test binary running the ignored test `helper`, which writes the pid of the
    /// `sleep` it started (as a child or deeper) to the returned file.
    fn start_helper(helper: &str) -> (Child, std::path::PathBuf) {
        let pid_file = std::env::temp_dir().join(format!("deform-{helper}-{}", std::process::id()));
        let _ = std::fs::remove_file(&pid_file);
        let parent = Command::new(std::env::current_exe().unwrap())
            .args(["--exact", &format!("child::tests::{helper}"), "--ignored"])
            .arg("--nocapture")
            .env(PID_FILE_ENV, &pid_file)
            .spawn()
            .unwrap();
        (parent, pid_file)
    }

    /// Where a helper writes its sleep's pid.
    const PID_FILE_ENV: &str = "DEFORM_CHILD_TEST_PID_FILE";

    /// The pid a helper wrote to `pid_file`, once that process runs `sleep` (a shell's `$!` is
    /// written when it has forked, maybe before the fork has become `sleep`).
    fn sleep_started_by(pid_file: &std::path::Path) -> u32 {
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let pid = std::fs::read_to_string(pid_file)
                .ok()
                .and_then(|t| t.trim().parse().ok());
            if let Some(pid) = pid.filter(|&p| process_info(p).is_some_and(|p| p.name == "sleep")) {
                assert!(is_running(pid), "sleep is not running");
                return pid;
            }
            assert!(Instant::now() < deadline, "the helper never started sleep");
            thread::sleep(Duration::from_millis(20));
        }
    }

    /// SIGKILLs `parent` and waits up to 5 s for `sleeper` to be gone.
    fn kill_and_see_it_die(parent: &mut Child, sleeper: u32) {
        parent.kill().unwrap();
        parent.wait().unwrap();
        let deadline = Instant::now() + Duration::from_secs(5);
        while is_running(sleeper) {
            assert!(
                Instant::now() < deadline,
                "sleep ({sleeper}) outlived its SIGKILLed parent"
            );
            thread::sleep(Duration::from_millis(20));
        }
    }

    /// `pid`'s process group, from `/proc/PID/stat`.
    fn process_group(pid: u32) -> Option<u32> {
        let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
        stat.rsplit_once(')')?
            .1
            .split_whitespace()
            .nth(2)?
            .parse()
            .ok()
    }

    /// Run by [`a_trees_grandchild_dies_when_its_parent_is_killed`] only: a tree whose command
    /// starts `sleep 60` in its turn and writes its pid.
    #[test]
    #[ignore = "a helper process of a_trees_grandchild_dies_when_its_parent_is_killed"]
    fn helper_parent_that_spawns_a_tree() {
        let Some(pid_file) = std::env::var_os(PID_FILE_ENV) else {
            return;
        };
        // bash's job control (`set -m`) puts sleep in a process group of its own, as ninja
        // does each compiler.
        let mut cmd = Command::new("bash");
        cmd.args(["-c", "set -m; sleep 60 & echo $! > \"$1\"; wait", "sh"])
            .arg(pid_file);
        let mut child = spawn_tree(tree(&cmd)).unwrap();
        // Killed while it waits.
        let _ = child.wait();
    }

    /// Run by [`a_child_dies_when_its_parent_is_killed`] only: starts `sleep 60`, writes its pid,
    /// and waits to be killed.
    #[test]
    #[ignore = "a helper process of a_child_dies_when_its_parent_is_killed"]
    fn helper_parent_that_spawns_sleep() {
        let Some(pid_file) = std::env::var_os(PID_FILE_ENV) else {
            return;
        };
        let mut cmd = Command::new("sleep");
        cmd.arg("60");
        let mut child = spawn(cmd).unwrap();
        std::fs::write(pid_file, child.id().to_string()).unwrap();
        // Killed while it waits.
        let _ = child.wait();
    }
}
