"""flowloop install on copies of real trees: dry-run, install, uninstall."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from devtools import stack
from flowloop import cli
from flowloop.host import install

PROJECT = stack.PROJECT


def snapshot(root: Path) -> dict:
    """Every path under root with its bytes (or link target) and mode."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            if install.BACKUP_SUFFIX in name:
                continue  # install's backups of config files: documented
            path = Path(dirpath) / name
            rel = str(path.relative_to(root))
            st = path.lstat()
            if path.is_symlink():
                out[rel] = ("link", os.readlink(path))
            elif stat.S_ISREG(st.st_mode):
                out[rel] = ("file", path.read_bytes(), st.st_mode)
            else:
                out[rel] = ("dir", st.st_mode)
    return out


@pytest.fixture
def klipper_tree(tmp_path):
    """A copy of the user's Klipper when there is one, else its skeleton."""
    tree = tmp_path / "klipper"
    if stack.missing_klipper_reason() is None:
        kp = stack.klipper_path()
        tree.mkdir()
        for rel in ("klippy", "src", ".git"):
            shutil.copytree(kp / rel, tree / rel, symlinks=True,
                            ignore=shutil.ignore_patterns("__pycache__", "objects"))
    else:
        (tree / "klippy" / "extras").mkdir(parents=True)
        (tree / "klippy" / "klippy.py").write_text("")
        (tree / "src").mkdir()
        (tree / "src" / "Makefile").write_text("src-y += sched.c\n")
        (tree / "src" / "Kconfig").write_text(
            f"config WANT_SPI\n    bool\n{install.LIMITED_MENU}\nendmenu\n")
        (tree / ".git" / "info").mkdir(parents=True)
        (tree / ".git" / "info" / "exclude").write_text("# git ls-files\n")
    return tree


def _moonraker_package(dest: Path) -> None:
    """Moonraker's own package from the test venv when built, else a stand-in."""
    built = sorted(stack.cache_dir().glob("moonraker-venv-*/lib/python*/"
                                          "site-packages/moonraker"))
    if built:
        shutil.copytree(built[-1], dest, symlinks=True,
                        ignore=shutil.ignore_patterns("__pycache__", "flowloop.py",
                                                      "flowloop"))
    else:
        (dest / "components").mkdir(parents=True)
        (dest / "__init__.py").write_text("")
        (dest / "components" / "__init__.py").write_text("")
        (dest / "components" / "klippy_apis.py").write_text("# stand-in\n")


@pytest.fixture
def moonraker_checkout(tmp_path):
    """Moonraker laid out as a git checkout (what KIAUH installs)."""
    root = tmp_path / "moonraker"
    _moonraker_package(root / "moonraker")
    (root / ".git" / "info").mkdir(parents=True)
    (root / ".git" / "info" / "exclude").write_text("")
    return root


@pytest.fixture
def moonraker_venv_copy(tmp_path):
    """A virtualenv whose python imports moonraker (pip-installed Moonraker)."""
    venv = tmp_path / "moonraker-env"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)],
                   check=True)
    _moonraker_package(next(venv.glob("lib/python*/site-packages")) / "moonraker")
    return venv


@pytest.fixture
def config_dir(tmp_path):
    cfg = tmp_path / "printer_data" / "config"
    cfg.mkdir(parents=True)
    (cfg / "moonraker.conf").write_text("[server]\nhost: 0.0.0.0")  # no final newline
    return cfg


def run_install(*args: str) -> int:
    return cli.main(["install", *args])


def args_for(klipper, moonraker, config_dir):
    return ["--klipper", str(klipper), "--moonraker", str(moonraker),
            "--config-dir", str(config_dir)]


@pytest.mark.parametrize("moonraker_form", ["moonraker_checkout",
                                            "moonraker_venv_copy"])
def test_dry_run_then_install_then_uninstall_restores_every_byte(
        klipper_tree, moonraker_form, config_dir, capsys, request):
    moonraker = request.getfixturevalue(moonraker_form)
    trees = (klipper_tree, moonraker, config_dir)
    before = [snapshot(t) for t in trees]
    args = args_for(*trees)

    assert run_install(*args, "--dry-run") == 0
    assert [snapshot(t) for t in trees] == before
    assert "would link" in capsys.readouterr().out

    assert run_install(*args) == 0
    extras = klipper_tree / "klippy" / "extras" / "flowloop.py"
    assert extras.is_symlink()
    assert extras.resolve() == PROJECT / "klippy_extras" / "flowloop.py"
    comp = install.moonraker_components_dir(moonraker) / "flowloop"
    assert comp.is_symlink()  # the package is linked whole, like a module
    assert comp.resolve() == PROJECT / "moonraker_components" / "flowloop"
    assert (comp / "__init__.py").is_file()
    conf = (config_dir / "moonraker.conf").read_text()
    assert "[update_manager flowloop]" in conf
    assert "managed_services: klipper moonraker" in conf
    exclude = (klipper_tree / ".git" / "info" / "exclude").read_text()
    assert "/klippy/extras/flowloop.py" in exclude
    installed = [snapshot(t) for t in trees]

    assert run_install(*args) == 0  # idempotent
    assert [snapshot(t) for t in trees] == installed
    assert "nothing to do" in capsys.readouterr().out

    assert run_install(*args, "--uninstall") == 0
    assert [snapshot(t) for t in trees] == before


def test_the_firmware_patch_adds_makefile_and_kconfig_lines(klipper_tree, tmp_path):
    """What flowloop firmware does to its copy (never to the checkout)."""
    source = tmp_path / "source"
    shutil.copytree(PROJECT / "klippy_extras", source / "klippy_extras")
    (source / "mcu_sensor").mkdir()
    (source / "mcu_sensor" / install.SENSOR_C).write_text("/* sensor */\n")
    before = snapshot(klipper_tree)
    install.apply(install.plan_firmware(klipper_tree, source))
    makefile = (klipper_tree / "src" / "Makefile").read_text()
    kconfig = (klipper_tree / "src" / "Kconfig").read_text()
    assert install.MAKEFILE_LINES in makefile
    # the prompt sits inside the limited-code-size menu, the default outside it
    menu = kconfig.index(install.LIMITED_MENU)
    assert kconfig.index(install.KCONFIG_HIDDEN) < menu
    prompt = kconfig.index(install.KCONFIG_PROMPT)
    assert menu < prompt < kconfig.index("endmenu", menu)
    assert (klipper_tree / "src" / install.SENSOR_C).is_symlink()
    install.apply(install.plan_firmware(klipper_tree, source, uninstall=True))
    assert snapshot(klipper_tree) == before


def test_without_sensor_source_install_leaves_the_build_files_alone(klipper_tree,
                                                                    tmp_path):
    source = tmp_path / "source"
    shutil.copytree(PROJECT / "klippy_extras", source / "klippy_extras")
    makefile = (klipper_tree / "src" / "Makefile").read_bytes()
    install.apply(install.plan_klipper(klipper_tree, source))
    assert (klipper_tree / "src" / "Makefile").read_bytes() == makefile
    assert not (klipper_tree / "src" / install.SENSOR_C).exists()


def test_a_file_not_ending_in_newline_round_trips(tmp_path):
    text = "[server]\nhost: 1"
    added = install.put_block(text, "x", "a: 1\n")
    assert added.startswith(text + "\n")
    assert install.drop_block(added, "x") == text


def test_an_older_block_is_refreshed_in_place():
    text = install.put_block("head\n", "x", "old\n") + "tail\n"
    refreshed = install.put_block(text, "x", "new\n")
    assert refreshed == install.put_block("head\n", "x", "new\n") + "tail\n"


@pytest.mark.parametrize("make_bad, message", [
    (lambda t: t / "nope", "no such directory"),
    (lambda t: (t / "plain").mkdir() or t / "plain", "is not a Klipper tree"),
])
def test_a_wrong_klipper_path_is_one_line_and_changes_nothing(
        tmp_path, moonraker_checkout, config_dir, capsys, make_bad, message):
    bad = make_bad(tmp_path)
    before = snapshot(tmp_path)
    assert run_install(*args_for(bad, moonraker_checkout, config_dir)) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert snapshot(tmp_path) == before


def test_a_foreign_file_in_the_way_is_refused(klipper_tree, moonraker_checkout,
                                              config_dir, capsys):
    (klipper_tree / "klippy" / "extras" / "flowloop.py").write_text("# someone's\n")
    before = snapshot(klipper_tree)
    assert run_install(*args_for(klipper_tree, moonraker_checkout, config_dir)) == 2
    assert "is not flowloop's link" in capsys.readouterr().err
    assert snapshot(klipper_tree) == before


@pytest.fixture
def read_only(tmp_path):
    """Make a file unwritable even for root (chattr +i), else by its mode."""
    made = []

    def make(path: Path) -> None:
        if os.geteuid() == 0:
            if subprocess.run(["chattr", "+i", str(path)],
                              capture_output=True).returncode != 0:
                pytest.skip("running as root and chattr +i is not available here")
            made.append(path)
        else:
            path.chmod(0o444)
    yield make
    for path in made:
        subprocess.run(["chattr", "-i", str(path)], check=True)


def test_an_unwritable_moonraker_conf_is_refused_before_anything_changes(
        klipper_tree, moonraker_checkout, config_dir, capsys, read_only):
    read_only(config_dir / "moonraker.conf")
    before = snapshot(klipper_tree)
    assert run_install(*args_for(klipper_tree, moonraker_checkout, config_dir)) == 2
    err = capsys.readouterr().err.strip()
    assert "moonraker.conf: not writable" in err and "\n" not in err
    assert snapshot(klipper_tree) == before


def test_a_failed_step_rolls_back_the_steps_before_it(klipper_tree, moonraker_checkout,
                                                      config_dir, monkeypatch):
    """What root's permissions hide: a write that fails midway undoes the rest."""
    before = [snapshot(t) for t in (klipper_tree, moonraker_checkout, config_dir)]
    real = install._write_atomic

    def failing(path, text):
        if path.name == "moonraker.conf":
            raise PermissionError(13, "Permission denied", str(path))
        real(path, text)
    monkeypatch.setattr(install, "_write_atomic", failing)
    trees = (klipper_tree, moonraker_checkout, config_dir)
    assert run_install(*args_for(*trees)) == 2
    assert [snapshot(t) for t in trees] == before


def test_a_missing_moonraker_conf_is_named(klipper_tree, moonraker_checkout, tmp_path,
                                            capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert run_install(*args_for(klipper_tree, moonraker_checkout, empty)) == 2
    assert "moonraker.conf: no such file" in capsys.readouterr().err


def test_a_venv_is_asked_where_its_moonraker_lives(moonraker_venv_copy):
    site = next(moonraker_venv_copy.glob("lib/python*/site-packages"))
    assert install.moonraker_components_dir(moonraker_venv_copy).resolve() == (
        site / "moonraker" / "components").resolve()


def test_a_venv_without_moonraker_is_refused(tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)],
                   check=True)
    with pytest.raises(install.InstallError, match="cannot import moonraker"):
        install.moonraker_components_dir(venv)


def test_a_users_own_update_manager_section_is_kept(config_dir):
    conf = config_dir / "moonraker.conf"
    conf.write_text("[update_manager flowloop]\ntype: git_repo\npath: ~/mine\n")
    install.apply(install.plan_moonraker_conf(config_dir, PROJECT))
    text = conf.read_text()
    assert text.count("[update_manager flowloop]") == 1 and "~/mine" in text


def test_links_of_a_module_an_older_flowloop_had_are_removed(klipper_tree, tmp_path):
    """Upgrade path: a module renamed or dropped since the last install."""
    source = tmp_path / "source"
    shutil.copytree(PROJECT / "klippy_extras", source / "klippy_extras")
    before = snapshot(klipper_tree)
    (source / "klippy_extras" / "old_module.py").write_text("# gone soon\n")
    install.apply(install.plan_klipper(klipper_tree, source.resolve()))
    old_link = klipper_tree / "klippy" / "extras" / "old_module.py"
    assert old_link.is_symlink()
    (source / "klippy_extras" / "old_module.py").unlink()  # the new version
    install.apply(install.plan_klipper(klipper_tree, source.resolve()))
    assert not old_link.is_symlink()
    install.apply(install.plan_klipper(klipper_tree, source.resolve(), uninstall=True))
    assert snapshot(klipper_tree) == before


def test_a_link_into_someone_elses_tree_is_not_stale(klipper_tree, tmp_path):
    other = tmp_path / "other_plugin.py"
    other.write_text("")
    link = klipper_tree / "klippy" / "extras" / "other_plugin.py"
    link.symlink_to(other)
    install.apply(install.plan_klipper(klipper_tree, PROJECT))
    install.apply(install.plan_klipper(klipper_tree, PROJECT, uninstall=True))
    assert link.is_symlink()


def test_a_worktree_excludes_in_the_main_repositorys_git_dir(tmp_path):
    main_git = tmp_path / "repo" / ".git"
    (main_git / "info").mkdir(parents=True)
    (main_git / "worktrees" / "wt").mkdir(parents=True)
    (main_git / "worktrees" / "wt" / "commondir").write_text("../..\n")
    tree = tmp_path / "wt"
    tree.mkdir()
    (tree / ".git").write_text(f"gitdir: {main_git / 'worktrees' / 'wt'}\n")
    assert install.git_exclude_file(tree) == (main_git / "info" / "exclude").resolve()


def test_install_reports_what_it_did_only_after_doing_it(
        klipper_tree, moonraker_checkout, config_dir, capsys, monkeypatch):
    def failing(path, text):
        raise PermissionError(13, "Permission denied", str(path))
    monkeypatch.setattr(install, "_write_atomic", failing)
    assert run_install(*args_for(klipper_tree, moonraker_checkout, config_dir)) == 2
    out = capsys.readouterr().out
    assert "link" not in out


def test_a_component_module_an_older_flowloop_linked_becomes_the_package(
        moonraker_checkout, tmp_path):
    """Upgrade path: flowloop.py (one module) was split into flowloop/."""
    source = (tmp_path / "source").resolve()
    shutil.copytree(PROJECT / "moonraker_components", source / "moonraker_components",
                    ignore=shutil.ignore_patterns("__pycache__"))
    (source / "moonraker_components" / "flowloop.py").write_text("# old\n")
    components = install.moonraker_components_dir(moonraker_checkout)
    before = snapshot(moonraker_checkout)
    # what the older flowloop left: a link to its module, excluded from git
    (components / "flowloop.py").symlink_to(source / "moonraker_components"
                                            / "flowloop.py")
    (source / "moonraker_components" / "flowloop.py").unlink()
    install.apply(install.plan_moonraker(moonraker_checkout, source))
    assert not (components / "flowloop.py").is_symlink()
    assert os.readlink(components / "flowloop") == str(
        source / "moonraker_components" / "flowloop")
    exclude = (moonraker_checkout / ".git" / "info" / "exclude").read_text()
    assert "/moonraker/components/flowloop\n" in exclude
    install.apply(install.plan_moonraker(moonraker_checkout, source, uninstall=True))
    assert snapshot(moonraker_checkout) == before


def test_both_forms_of_component_are_found(tmp_path):
    comps = tmp_path / "moonraker_components"
    (comps / "pkg").mkdir(parents=True)
    (comps / "pkg" / "__init__.py").write_text("")
    (comps / "module.py").write_text("")
    (comps / "data").mkdir()  # no __init__.py: not a package
    (comps / "__pycache__").mkdir()
    (comps / "_private.py").write_text("")
    assert [p.name for p in install.moonraker_components(tmp_path)] == [
        "module.py", "pkg"]


# --- Kalico: plugins and a firmware extra, none of Kalico's files edited -----

def kalico_path() -> Path:
    return Path(os.environ.get("KALICO_PATH", "~/kalico")).expanduser()


@pytest.fixture
def kalico_tree(tmp_path):
    """A copy of the user's Kalico when there is one, else its skeleton."""
    tree = tmp_path / "kalico"
    kp = kalico_path()
    if install.is_kalico(kp):
        tree.mkdir()
        for rel in ("klippy", "src", "scripts"):
            shutil.copytree(kp / rel, tree / rel, symlinks=True,
                            ignore=shutil.ignore_patterns("__pycache__", "out"))
        for rel in ("Makefile", ".gitignore"):
            shutil.copy(kp / rel, tree / rel)
        (tree / ".git" / "info").mkdir(parents=True)
        (tree / ".git" / "info" / "exclude").write_text("# git ls-files\n")
    else:
        (tree / "klippy" / "extras").mkdir(parents=True)
        (tree / "klippy" / "plugins").mkdir()
        (tree / "klippy" / "plugins" / "__init__.py").write_text("# plugins\n")
        (tree / "klippy" / "klippy.py").write_text("")
        (tree / "src" / "extras").mkdir(parents=True)
        (tree / "src" / "extras" / ".gitignore").write_text("*\n")
        (tree / "src" / "Makefile").write_text("src-y += sched.c\n")
        (tree / "src" / "Kconfig").write_text('source "src/extras/Kconfig"\n')
        (tree / "scripts").mkdir()
        (tree / "scripts" / "find-firmware-extras.sh").write_text("#!/bin/sh\n")
    return tree


def test_kalico_is_told_from_klipper(kalico_tree, klipper_tree):
    assert install.is_kalico(kalico_tree) and install.host_name(kalico_tree) == "Kalico"
    assert not install.is_kalico(klipper_tree)


def test_kalico_install_uses_plugins_and_a_firmware_extra_and_uninstall_restores(
        kalico_tree, moonraker_checkout, config_dir, capsys):
    trees = (kalico_tree, moonraker_checkout, config_dir)
    before = [snapshot(t) for t in trees]
    args = args_for(*trees)
    assert run_install(*args, "--dry-run") == 0
    assert [snapshot(t) for t in trees] == before
    assert "would make folder" in capsys.readouterr().out

    assert run_install(*args) == 0
    out = capsys.readouterr().out
    assert "Firmware Extras" in out and "restart kalico" in out
    # the simulated sensor and autotemp run on Kalico too: nothing to note
    assert "motion_queuing" not in out
    plugin = kalico_tree / "klippy" / "plugins" / "flowloop.py"
    assert plugin.is_symlink()
    assert plugin.resolve() == PROJECT / "klippy_extras" / "flowloop.py"
    assert not (kalico_tree / "klippy" / "extras" / "flowloop.py").exists()
    extra = kalico_tree / "src" / "extras" / install.KALICO_EXTRA
    assert (extra / install.SENSOR_C).resolve() == (
        PROJECT / "mcu_sensor" / install.SENSOR_C)
    assert (extra / "Kconfig").read_text() == install.KALICO_KCONFIG
    assert (extra / "Makefile").read_text() == install.KALICO_MAKEFILE
    # no file of Kalico's changed: only new paths in the two add-on folders
    installed = snapshot(kalico_tree)
    added = set(installed) - set(before[0])
    assert {k: v for k, v in installed.items() if k not in added} == before[0]
    assert all(p.startswith(("klippy/plugins/", "src/extras/flowloop")) for p in added)

    assert run_install(*args) == 0  # idempotent
    assert snapshot(kalico_tree) == installed
    assert run_install(*args, "--uninstall") == 0
    assert [snapshot(t) for t in trees] == before


def test_kalicos_make_finds_the_extra_and_menuconfig_offers_it(kalico_tree):
    """Kalico's own scripts: find-firmware-extras.sh sources our Kconfig and
    Makefile, and olddefconfig turns the sensor on for an SPI board."""
    if not install.is_kalico(kalico_path()):
        pytest.skip(f"no Kalico checkout at {kalico_path()} (set KALICO_PATH)")
    (kalico_tree / "lib").symlink_to(kalico_path() / "lib")
    install.apply(install.plan_klipper(kalico_tree, PROJECT))
    shutil.copy(kalico_path() / "test" / "configs" / "atmega2560.config",
                kalico_tree / ".config")
    proc = subprocess.run(["make", "olddefconfig"], cwd=kalico_tree,
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    extras = kalico_tree / "src" / "extras"
    assert 'source "src/extras/flowloop/Kconfig"' in (extras / "Kconfig").read_text()
    assert "include src/extras/flowloop/Makefile" in (extras / "Makefile").read_text()
    config = (kalico_tree / ".config").read_text()
    assert "CONFIG_WANT_SENSOR_EMS22=y" in config
    assert "CONFIG_NEED_SENSOR_BULK=y" in config


def test_a_klipper_style_install_in_kalico_is_moved_to_the_plugin_folder(
        kalico_tree, tmp_path):
    source = (tmp_path / "source").resolve()
    shutil.copytree(PROJECT / "klippy_extras", source / "klippy_extras")
    before = snapshot(kalico_tree)
    old = kalico_tree / "klippy" / "extras" / "flowloop.py"
    old.symlink_to(source / "klippy_extras" / "flowloop.py")  # an older install
    install.apply(install.plan_klipper(kalico_tree, source))
    assert not old.is_symlink()  # Kalico refuses a name in extras and plugins
    assert (kalico_tree / "klippy" / "plugins" / "flowloop.py").is_symlink()
    install.apply(install.plan_klipper(kalico_tree, source, uninstall=True))
    assert snapshot(kalico_tree) == before


def test_a_kalico_module_of_the_same_name_is_refused(kalico_tree):
    (kalico_tree / "klippy" / "extras" / "flowloop.py").write_text("# Kalico's\n")
    before = snapshot(kalico_tree)
    with pytest.raises(install.InstallError, match="Kalico has a module named"):
        install.plan_klipper(kalico_tree, PROJECT)
    assert snapshot(kalico_tree) == before


def test_a_users_file_in_the_extra_folder_is_kept_at_uninstall(kalico_tree):
    install.apply(install.plan_klipper(kalico_tree, PROJECT))
    extra = kalico_tree / "src" / "extras" / install.KALICO_EXTRA
    (extra / "notes.txt").write_text("mine\n")
    install.apply(install.plan_klipper(kalico_tree, PROJECT, uninstall=True))
    assert sorted(p.name for p in extra.iterdir()) == ["notes.txt"]


def test_a_foreign_extra_folder_is_refused(kalico_tree):
    extra = kalico_tree / "src" / "extras" / install.KALICO_EXTRA
    extra.mkdir()
    (extra / "Kconfig").write_text("config SOMEONE_ELSES\n    bool\n")
    before = snapshot(kalico_tree)
    with pytest.raises(install.InstallError, match="is not flowloop's"):
        install.apply(install.plan_klipper(kalico_tree, PROJECT))
    assert snapshot(kalico_tree) == before


# --- installed from a wheel: the bundled copy, no git updater -----------------

def test_an_installed_package_links_its_bundled_copy(tmp_path, monkeypatch):
    site = tmp_path / "site-packages"
    shutil.copytree(PROJECT / "flowloop", site / "flowloop",
                    ignore=shutil.ignore_patterns("__pycache__"))
    bundle = site / "flowloop" / install.BUNDLE
    shutil.copytree(PROJECT / "klippy_extras", bundle / "klippy_extras")
    monkeypatch.setattr(install, "__file__",
                        str(site / "flowloop" / "host" / "install.py"))
    assert install.source_tree() == bundle
    (bundle / "klippy_extras" / "flowloop.py").unlink()
    shutil.rmtree(bundle / "klippy_extras")
    with pytest.raises(install.InstallError, match="reinstall flowloop"):
        install.source_tree()


def test_no_update_manager_block_for_a_pip_installed_flowloop(config_dir, tmp_path):
    bundle = tmp_path / "bundle"
    (bundle / "klippy_extras").mkdir(parents=True)
    conf = config_dir / "moonraker.conf"
    install.apply(install.plan_moonraker_conf(config_dir, bundle))
    assert "update_manager" not in conf.read_text()
    install.apply(install.plan_moonraker_conf(config_dir, PROJECT))  # a checkout's
    assert "[update_manager flowloop]" in conf.read_text()
    install.apply(install.plan_moonraker_conf(config_dir, bundle))  # now a wheel's
    assert "update_manager" not in conf.read_text()
    assert "[flowloop]" in conf.read_text()


def test_without_klipper_path_the_default_is_klipper_else_kalico(tmp_path,
                                                                 monkeypatch):
    from flowloop.cli import install as cli_install
    monkeypatch.delenv("KLIPPER_PATH", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    (tmp_path / "kalico").mkdir()
    assert cli_install.default_klipper().expanduser() == tmp_path / "kalico"
    (tmp_path / "klipper").mkdir()
    assert cli_install.default_klipper().expanduser() == tmp_path / "klipper"
    monkeypatch.setenv("KLIPPER_PATH", str(tmp_path / "elsewhere"))
    assert cli_install.default_klipper() == tmp_path / "elsewhere"


def test_a_dry_run_says_each_change_once_and_what_it_adds(klipper_tree, capsys):
    assert install.mcu_sources(install.source_tree())  # the Makefile gets lines
    assert run_install("--klipper", str(klipper_tree), "--no-moonraker",
                       "--config-dir", str(klipper_tree), "--dry-run") == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines and all(line.startswith("would ") for line in lines)
    for line in lines:   # the path once: "would link A -> B", not "...: A"
        path = line.split()[2].rstrip(":")
        assert line.count(path) == 1, line
    # the checkout's tracked files are not touched: no src/ edit is planned
    assert not any("/src/" in line for line in lines)


def test_without_moonraker_only_klipper_is_to_be_restarted(klipper_tree, tmp_path,
                                                          capsys):
    where = ("--klipper", str(klipper_tree), "--config-dir", str(tmp_path))
    assert run_install(*where, "--no-moonraker") == 0
    last = capsys.readouterr().out.splitlines()[-1]
    assert last == "restart klipper to load the change"
    assert run_install(*where, "--no-moonraker", "--uninstall") == 0


# --- Klipper stays updatable: nothing git tracks is changed ------------------

# What Moonraker's update manager counts as source (git_deploy.py SRC_EXTS):
# an untracked file with one of these suffixes makes the repo not pristine.
MOONRAKER_SRC_EXTS = (".py", ".c", ".cpp", ".h", ".s", ".S", ".js", ".sh")


def git_out(tree: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(tree), *args], check=True,
                          capture_output=True, text=True).stdout


def update_manager_view(tree: Path) -> dict:
    """The repo as Moonraker's git_deploy judges it: `git describe --dirty`,
    modified files and untracked source files from `git status --porcelain`."""
    described = git_out(tree, "describe", "--always", "--tags", "--long",
                        "--dirty").strip()
    modified, untracked = [], []
    for line in git_out(tree, "status", "--porcelain", "-b").splitlines():
        prefix, _, name = line.strip().partition(" ")
        if prefix == "M":
            modified.append(name.strip())
        elif prefix == "??" and Path(name.strip()).suffix in MOONRAKER_SRC_EXTS:
            untracked.append(name.strip())
    return {"dirty": described.endswith("-dirty"), "modified": modified,
            "untracked": untracked}


def clone_of(path: Path, where: Path) -> Path:
    """A git clone of a user's checkout (objects shared, nothing written there)."""
    if not (path / ".git").exists():
        pytest.skip(f"no git checkout at {path}")
    subprocess.run(["git", "clone", "-q", "--shared", str(path), str(where)],
                   check=True)
    return where


@pytest.fixture
def klipper_clone(tmp_path):
    return clone_of(stack.klipper_path(), tmp_path / "klipper")


@pytest.mark.parametrize("host", ["klipper", "kalico"])
def test_after_install_the_checkout_is_pristine_as_moonraker_judges_it(
        host, tmp_path, capsys):
    tree = clone_of(stack.klipper_path() if host == "klipper" else kalico_path(),
                    tmp_path / host)
    where = ("--klipper", str(tree), "--config-dir", str(tmp_path))
    assert run_install(*where, "--no-moonraker") == 0
    assert update_manager_view(tree) == {"dirty": False, "modified": [],
                                         "untracked": []}
    assert (tree / "klippy" / ("plugins" if host == "kalico" else "extras")
            / "flowloop.py").is_symlink()
    assert run_install(*where, "--no-moonraker", "--uninstall") == 0
    assert git_out(tree, "status", "--porcelain", "--ignored") == ""


def test_an_install_over_an_older_one_restores_klippers_src_files_and_says_so(
        klipper_clone, tmp_path, capsys):
    kconfig = (klipper_clone / "src" / "Kconfig").read_bytes()
    makefile = (klipper_clone / "src" / "Makefile").read_bytes()
    # what an older flowloop install left: src/ edited, its links excluded
    install.apply(install.plan_firmware(klipper_clone, PROJECT))
    install._exclude_changes(changes := [], klipper_clone,
                             [f"src/{install.SENSOR_C}"], uninstall=False)
    install.apply(changes)
    assert update_manager_view(klipper_clone)["modified"] == ["src/Kconfig",
                                                              "src/Makefile"]
    assert run_install("--klipper", str(klipper_clone), "--config-dir",
                       str(tmp_path), "--no-moonraker") == 0
    out = capsys.readouterr().out
    assert (klipper_clone / "src" / "Kconfig").read_bytes() == kconfig
    assert (klipper_clone / "src" / "Makefile").read_bytes() == makefile
    assert not (klipper_clone / "src" / install.SENSOR_C).exists()
    assert update_manager_view(klipper_clone) == {"dirty": False, "modified": [],
                                                  "untracked": []}
    said = [line for line in out.splitlines() if "left by an older flowloop" in line]
    assert all("/src/" in line for line in said)
    assert {line.split(" (")[0] for line in said} >= {
        f"remove the EMS22 sensor option from {klipper_clone}/src/Kconfig",
        f"remove the EMS22 sensor source from {klipper_clone}/src/Makefile",
        f"remove link {klipper_clone}/src/{install.SENSOR_C}"}


def test_flowloop_firmware_builds_the_sensor_from_a_copy_and_keeps_the_checkout_clean(
        klipper_clone, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    shutil.copy(klipper_clone / "test" / "configs" / "linuxprocess.config",
                klipper_clone / ".config")
    assert cli.main(["firmware", "--klipper", str(klipper_clone), "olddefconfig"]) == 0
    assert cli.main(["firmware", "--klipper", str(klipper_clone), "--",
                     f"-j{os.cpu_count() or 2}"]) == 0
    out = capsys.readouterr().out
    copy = tmp_path / "cache" / "flowloop" / "firmware" / "klipper"
    assert f"in {copy}, a copy of {klipper_clone}" in out
    # .config and out/ where Klipper keeps them; the EMS22 command is built in
    assert "CONFIG_WANT_SENSOR_EMS22=y" in (klipper_clone / ".config").read_text()
    dictionary = (klipper_clone / "out" / "klipper.dict").read_text()
    assert "config_ems22" in dictionary and "query_ems22" in dictionary
    # the firmware's version is the checkout's
    head = git_out(klipper_clone, "describe", "--always", "--tags", "--long").strip()
    assert f"{head}-flowloop" in dictionary
    assert update_manager_view(klipper_clone) == {"dirty": False, "modified": [],
                                                  "untracked": []}
    # a Klipper update (a new commit) reaches the next build's copy
    (klipper_clone / "src" / "Kconfig").write_text(
        (klipper_clone / "src" / "Kconfig").read_text() + "# updated upstream\n")
    git_out(klipper_clone, "-c", "user.name=t", "-c", "user.email=t@t", "commit",
            "-qam", "an update")
    assert cli.main(["firmware", "--klipper", str(klipper_clone), "olddefconfig"]) == 0
    assert "# updated upstream" in (copy / "src" / "Kconfig").read_text()
    assert "WANT_SENSOR_EMS22" in (copy / "src" / "Kconfig").read_text()


def test_flowloop_firmware_on_kalico_needs_the_installed_extra(tmp_path, kalico_tree,
                                                              capsys):
    args = ["firmware", "--klipper", str(kalico_tree), "--dry-run"]
    assert cli.main(args) == 2
    assert "run flowloop install first" in capsys.readouterr().err
    install.apply(install.plan_klipper(kalico_tree, PROJECT))
    assert cli.main(args) == 0
    assert f"would run make in {kalico_tree.resolve()}" in capsys.readouterr().out


# --- moonraker.conf: the component's own section -----------------------------

def test_install_adds_the_flowloop_section_with_a_backup_and_uninstall_takes_it_out(
        config_dir, capsys):
    conf = config_dir / "moonraker.conf"
    before = conf.read_bytes()
    install.apply(install.plan_moonraker_conf(config_dir, PROJECT))
    text = conf.read_text()
    assert "\n[flowloop]\n" in text and "[update_manager flowloop]" in text
    # the live page as a dashboard panel, at a URL relative to the UI's origin
    assert "\n[webcam flowloop]\n" in text
    assert "service: iframe\nstream_url: /server/flowloop/page/?panel=1\n" in text
    backups = list(config_dir.glob("moonraker.conf" + install.BACKUP_SUFFIX + "*"))
    assert [b.read_bytes() for b in backups] == [before]
    assert install.plan_moonraker_conf(config_dir, PROJECT) == []  # idempotent
    install.apply(install.plan_moonraker_conf(config_dir, PROJECT, uninstall=True))
    assert conf.read_bytes() == before
    assert install.plan_moonraker_conf(config_dir, PROJECT, uninstall=True) == []


def test_a_moonraker_conf_with_its_own_flowloop_section_is_left_alone(config_dir,
                                                                      capsys):
    conf = config_dir / "moonraker.conf"
    conf.write_text("[server]\nhost: 0.0.0.0\n\n[flowloop]  # mine\nhotend: v6\n")
    changes = install.plan_moonraker_conf(config_dir, PROJECT)
    notes = [c.what for c in changes if c.note]
    assert notes == [f"{conf} has a [flowloop] section of its own: left as it is"]
    install.apply(changes)
    assert conf.read_text().count("[flowloop]") == 1


def test_a_webcam_flowloop_of_the_users_own_is_left_alone(config_dir):
    conf = config_dir / "moonraker.conf"
    mine = "[server]\nhost: 0.0.0.0\n\n[webcam flowloop]\nservice: iframe\n" \
           "stream_url: http://printer.local/server/flowloop/page/\n"
    conf.write_text(mine)
    changes = install.plan_moonraker_conf(config_dir, PROJECT)
    assert [c.what for c in changes if c.note] == [
        f"{conf} has a [webcam flowloop] section of its own: left as it is"]
    install.apply(changes)
    assert conf.read_text().count("[webcam flowloop]") == 1
    install.apply(install.plan_moonraker_conf(config_dir, PROJECT, uninstall=True))
    assert conf.read_text() == mine


def test_a_commented_flowloop_section_is_not_counted_as_present(config_dir):
    conf = config_dir / "moonraker.conf"
    conf.write_text("[server]\nhost: 0.0.0.0\n#[flowloop]\n# [flowloop]\n")
    install.apply(install.plan_moonraker_conf(config_dir, PROJECT))
    assert "\n[flowloop]\n" in conf.read_text()


def test_a_crlf_moonraker_conf_stays_crlf_and_round_trips(config_dir):
    conf = config_dir / "moonraker.conf"
    conf.write_bytes(b"[server]\r\nhost: 0.0.0.0\r\n")
    install.apply(install.plan_moonraker_conf(config_dir, PROJECT))
    data = conf.read_bytes()
    assert b"[flowloop]\r\n" in data and b"\n" not in data.replace(b"\r\n", b"")
    install.apply(install.plan_moonraker_conf(config_dir, PROJECT, uninstall=True))
    assert conf.read_bytes() == b"[server]\r\nhost: 0.0.0.0\r\n"


# --- printer.cfg: uninstall leaves a configuration klippy starts with --------

PRINTER_CFG = """\
[include extras/*.cfg]

[printer]
kinematics: corexy

[flowloop]

[flow_sensor filament]
sensor_type: ems22
cs_pin: PA4
# my note on the sensor

[extruder]
max_temp: 260

[diff_ab_calibrate]
#*# <---------------------- SAVE_CONFIG ---------------------->
#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.
#*#
#*# [extruder]
#*# control = pid
#*#
#*# [flowrate_limiter]
#*# max_flow = 12.0
"""


@pytest.fixture
def printer_cfg(config_dir):
    """printer.cfg with flowloop's sections in it, in an included CRLF file,
    and in its SAVE_CONFIG block."""
    (config_dir / "printer.cfg").write_text(PRINTER_CFG)
    (config_dir / "extras").mkdir()
    (config_dir / "extras" / "flow.cfg").write_bytes(
        b"[autotemp]\r\nextruder: extruder\r\n\r\n[flow_sensor_simulation demo]"
        b"\r\nmelt_flow: 10\r\n\r\n[heater_bed]\r\nmax_temp: 100"
        b"\r\n\r\n[measure_profile]")  # no newline at the end
    (config_dir / "extras" / "other.cfg").write_text("[fan]\npin: PA8\n")
    return config_dir / "printer.cfg"


def flowloop_sections_klippy_reads(cfg: Path) -> list:
    from flowloop.host import klipper_config
    parsed = klipper_config.parse_config(cfg.read_text(), cfg)
    return [s for s in parsed.sections()
            if s.split()[0] in install.klippy_sections(PROJECT)]


def test_uninstall_comments_out_flowloop_sections_everywhere_and_install_restores(
        klipper_tree, printer_cfg, capsys):
    config_dir = printer_cfg.parent
    before = snapshot(config_dir)
    assert len(flowloop_sections_klippy_reads(printer_cfg)) == 7
    where = ("--klipper", str(klipper_tree), "--config-dir", str(config_dir),
             "--no-moonraker")
    assert run_install(*where) == 0
    capsys.readouterr()
    assert run_install(*where, "--uninstall") == 0
    out = capsys.readouterr().out
    assert flowloop_sections_klippy_reads(printer_cfg) == []
    from flowloop.host import klipper_config
    parsed = klipper_config.parse_config(printer_cfg.read_text(), printer_cfg)
    # everything else as it was, the SAVE_CONFIG block still read by klippy
    assert parsed.get("extruder", "max_temp") == "260"
    assert parsed.get("extruder", "control") == "pid"
    assert parsed.get("heater_bed", "max_temp") == "100"
    assert parsed.get("fan", "pin") == "PA8"
    assert klipper_config.split_autosave(printer_cfg.read_text())[1]
    flow = (config_dir / "extras" / "flow.cfg").read_bytes()
    assert b"\n" not in flow.replace(b"\r\n", b"")  # still CRLF
    assert f"comment out [flowloop], [flow_sensor filament], [diff_ab_calibrate]," \
           f" [flowrate_limiter] in {printer_cfg}" in out
    # the simulated sensor's own section too: its module is linked and gone
    assert "[autotemp], [flow_sensor_simulation demo], [measure_profile]" in out
    assert len(list(config_dir.rglob("*" + install.BACKUP_SUFFIX + "*"))) == 2
    assert not list(config_dir.rglob("*.cfg" + install.BACKUP_SUFFIX))
    # twice: nothing more to do
    assert run_install(*where, "--uninstall") == 0
    assert "nothing to do" in capsys.readouterr().out
    assert run_install(*where) == 0
    assert "restore [flowloop], [flow_sensor filament]" in capsys.readouterr().out
    assert snapshot(config_dir) == before
