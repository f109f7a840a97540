"""The command-line flags of every service and ``eonav`` command follow one set of rules:

- every service flag has an EONAV_* environment default named after the flag, and no two services read the same
  variable for different things (one env file per host must not change two services at once);
- every flag has a help text;
- a quantity with a unit carries the unit in its name (``--max-age-s``, not ``--max-age S``);
- one concept has one name everywhere;
- renamed flags keep their old spelling (hidden) and their old variable, with the same effect;
- the services' defaults for library settings are the library's own."""
import argparse
import importlib
import re

from eonav.app.cli import build_parser as cli_parser
from eonav.bus.node import build_parser as service_parser

SERVICES = {"camera_ingest": "camera", "mavlink_ingest": "mavlink", "sync": "sync", "locator": "locator",
            "obstacles": "obstacles"}   # module -> default instance name
SHARED_ON_PURPOSE = {"EONAV_REPLAY_SHIFT_US"}   # the same shift must reach every replay of one recording

# unit in a metavar -> the suffix the flag's name must end with
UNITS = {"S": "s", "MS": "ms", "US": "us", "M": "m", "HZ": "hz", "PX": "px", "DEG": "deg", "FPS": "fps"}
# float flags without a unit in the name, and why
NO_UNIT = {"--speed": "a factor of real time", "--min-scale": "a factor of the image size",
           "--min-confidence": "a ratio (inverse range over its sigma)", "--max-rel-std": "a ratio (sigma over range)",
           "--noise": "grey levels, the image's own unit", "--seconds": "the name is the unit",
           "--minutes": "the name is the unit", "--see-through-k": "a number of sigmas",
           "--duplicate-chi2": "a squared Mahalanobis distance", "--stereo-lead-k": "a number of sigmas",
           "--follow-k": "a number of sigmas", "--follow-fraction": "a fraction of the own speed",
           "--skipped-free-k": "a number of sigmas", "--jump-sigma-k": "a number of sigmas",
           "--layer-gap-rel": "a fraction of the range"}
# one name per concept: the parsers that have the concept all spell it so
CONCEPTS = {
    "--cv-threads": ("service locator", "eonav locate", "eonav bench locate", "eonav bench pipeline"),
    "--camera-id": ("service camera_ingest", "service locator"),
    "--wait-subscribers-s": ("service camera_ingest", "service mavlink_ingest"),
    "--keep-stamps": ("service camera_ingest", "service mavlink_ingest"),
    "--replay-shift-us": ("service camera_ingest", "service mavlink_ingest"),
    "--source": ("service camera_ingest", "service mavlink_ingest"),
    "--vehicle": ("eonav run", *(f"service {m}" for m in SERVICES)),
}
# a retired spelling that is still the visible name of a different concept somewhere
RETIRED_BUT_OTHER_CONCEPT = {("--camera", "eonav run")}   # eonav run --camera [ID=]SOURCE adds a camera ingest


def service_env_vars(name):
    p = argparse.ArgumentParser()
    importlib.import_module(f"eonav.services.{name}").add_arguments(p)
    out, dests_with_env = {}, set()
    actions = [a for a in p._actions if a.option_strings and a.dest != "help"]
    for a in actions:
        m = re.search(r"\(env (EONAV_[A-Z0-9_]+)", a.help or "")
        if m:
            out[m.group(1)] = a.option_strings[0]
            dests_with_env.add(a.dest)
    for a in actions:   # aliases (e.g. --grey for --encoding mono8) share the variable of their destination;
        if isinstance(a, argparse._AppendAction):   # repeatable flags (--method-param K=V ...) have none
            continue
        assert a.dest in dests_with_env, f"eonav.services.{name} {a.option_strings}: no EONAV_ environment default"
    return out


def test_env_variables_are_unique_across_services():
    seen = {}
    for name in SERVICES:
        for var, flag in service_env_vars(name).items():
            if var in seen and var not in SHARED_ON_PURPOSE:
                raise AssertionError(f"{var} is read by {seen[var]} and by services.{name} {flag}")
            seen[var] = f"eonav.services.{name} {flag}"
    assert len(seen) > 30


# ---- every parser of the project -----------------------------------------------------------------------

def _subparsers(p):
    for a in p._actions:
        if isinstance(a, argparse._SubParsersAction):
            yield from a.choices.items()


def all_parsers() -> dict:
    """{label: parser}: each service's full parser (its flags + the common ones) and every eonav (sub)command."""
    out = {}
    for module, name in SERVICES.items():
        out[f"service {module}"] = service_parser(name, importlib.import_module(f"eonav.services.{module}")
                                                  .add_arguments, module)
    for cmd, sp in _subparsers(cli_parser()):
        out[f"eonav {cmd}"] = sp
        for sub, ssp in _subparsers(sp):
            out[f"eonav {cmd} {sub}"] = ssp
    for module in ("eonav.bus.router", "eonav.app.demo", "eonav.app.bench_tracking"):          # python -m ...
        out[module] = argparse.ArgumentParser()
        importlib.import_module(module).add_arguments(out[module])
    return out


PARSERS = all_parsers()


def visible(p):
    return [a for a in p._actions if a.option_strings and a.help != argparse.SUPPRESS and a.dest != "help"]


def hidden(p):
    return [a for a in p._actions if a.option_strings and a.help == argparse.SUPPRESS]


def test_parsers_cover_the_services_and_commands():
    assert {"service camera_ingest", "service locator", "eonav run", "eonav locate", "eonav bench locate",
            "eonav bench pipeline", "eonav sim"} <= set(PARSERS)


def test_every_flag_has_help():
    for label, p in PARSERS.items():
        for a in p._actions:
            if a.dest == "help" or a.help == argparse.SUPPRESS or isinstance(a, argparse._SubParsersAction):
                continue                               # (a subcommand's help is its parser's, checked as such)
            text = re.sub(r"\(env EONAV_[A-Z0-9_]+; default .*\)$", "", a.help or "").strip()
            assert len(text.split()) >= 2, f"{label} {a.option_strings or a.dest}: no help"


def _unit_of(flag: str):
    return next((u for u in set(UNITS.values()) | {"seconds"} if flag == f"--{u}" or flag.endswith(f"-{u}")), None)


def test_units_are_in_the_names():
    for label, p in PARSERS.items():
        for a in visible(p):
            flag = a.option_strings[-1]
            for tok in re.split(r"[|,]", a.metavar or ""):
                if tok in UNITS:
                    assert flag.endswith("-" + UNITS[tok]) or flag == "--" + UNITS[tok], \
                        f"{label} {flag} {a.metavar}: the unit belongs in the name (…-{UNITS[tok]})"
            if a.type is float and flag not in NO_UNIT:
                assert _unit_of(flag), f"{label} {flag}: a float flag needs its unit in the name (or a NO_UNIT entry)"


def test_the_unit_rules_catch_a_flag_without_its_unit():
    p = argparse.ArgumentParser()
    p.add_argument("--max-age", type=float, metavar="S", help="oldest frame used")
    a = visible(p)[0]
    assert not a.option_strings[-1].endswith("-" + UNITS[a.metavar]) and not _unit_of(a.option_strings[-1])


def test_env_variables_follow_the_flag_names():
    for module in SERVICES:
        for a in visible(PARSERS[f"service {module}"]):
            env = getattr(a, "env", None)
            if env is None:                            # --shm / --no-shm, --warmup: read by hand, named in the help
                assert isinstance(a, (argparse.BooleanOptionalAction, argparse._AppendAction)) or \
                    a.const is not None, (module, a.option_strings)
                continue
            want = a.option_strings[-1][2:].upper().replace("-", "_")
            assert env == f"EONAV_{want}" or env.endswith(f"_{want}"), f"{module} {a.option_strings[-1]}: env {env}"


def test_one_name_per_concept():
    for flag, labels in CONCEPTS.items():
        for label in labels:
            names = {s for a in visible(PARSERS[label]) for s in a.option_strings}
            assert flag in names, f"{label}: {flag} missing"
    # the same name means the same thing everywhere: same kind of flag, same unit
    kinds = {}
    for label, p in PARSERS.items():
        for a in visible(p):
            kind = (type(a).__name__, sorted(t for t in re.split(r"[|,]", a.metavar or "") if t in UNITS))
            for s in a.option_strings:
                if s in ("-v", "--verbose", "--json", "--out", "--png", "--size", "--repeat", "--methods", "--method",
                         "--presets", "--seed", "--scale", "--camera"):
                    continue                           # per-command outputs and choices (different on purpose)
                first = kinds.setdefault(s, (label, kind))
                assert first[1] == kind, f"{s}: {first[0]} {first[1]} vs {label} {kind}"
    # a retired spelling is nowhere the visible name of a flag (it would mean two names for one concept, or one name
    # for two concepts)
    visible_names = {(s, label) for label, p in PARSERS.items() for a in visible(p) for s in a.option_strings}
    for label, p in PARSERS.items():
        for a in hidden(p):
            for s in a.option_strings:
                clash = {lab for (n, lab) in visible_names if n == s} - {lab for (n, lab) in RETIRED_BUT_OTHER_CONCEPT
                                                                         if n == s}
                assert not clash, f"{label}: retired {s} is a visible flag of {clash}"
    for names in (("--threads",), ("--rate",), ("--stale",), ("--max-age",), ("--health-period",)):
        assert not any(n in names for n, _ in visible_names), names


REQUIRED = {"eonav locate": ["pair.json", "--out", "x.npz"], "eonav fuse": ["seq.json", "--out", "x.npz"],
            "eonav record": ["out.mcap"], "eonav replay": ["in.mcap"]}


def _sample(a) -> list:
    if a.nargs == 0:
        return []
    if a.choices:
        return [str(list(a.choices)[-1])]
    return ["3"]


def test_old_spellings_parse_to_the_same_value():
    n = 0
    for label, p in PARSERS.items():
        new_by_dest = {a.dest: a for a in visible(p)}
        for old in hidden(p):
            new = new_by_dest[old.dest]
            v = _sample(new)
            prefix = REQUIRED.get(label, [])
            a_new = p.parse_args(prefix + [new.option_strings[0], *v])
            a_old = p.parse_args(prefix + [old.option_strings[0], *v])
            assert vars(a_old) == vars(a_new), (label, old.option_strings, new.option_strings)
            assert getattr(a_new, new.dest) != p.parse_args(prefix).__dict__[new.dest], (label, new.option_strings)
            n += 1
    assert n >= 25


def test_locate_old_threads_zero_still_means_opencv_default():
    p = PARSERS["eonav locate"]
    base = REQUIRED["eonav locate"]
    assert p.parse_args(base + ["--threads", "0"]).cv_threads == -1 == p.parse_args(base).cv_threads
    assert p.parse_args(base + ["--cv-threads", "0"]).cv_threads == 0


def test_old_environment_variables_are_still_read(monkeypatch):
    from eonav.app.commands import run as run_cmd
    from eonav.bus.node import add_common_arguments

    def fresh(label):
        p = argparse.ArgumentParser()
        if label == "eonav run":
            run_cmd.add_arguments(p)
        else:
            module = label.split()[1]
            importlib.import_module(f"eonav.services.{module}").add_arguments(p)
            add_common_arguments(p, SERVICES[module])
        return p

    n = 0
    for label in [*(f"service {m}" for m in SERVICES), "eonav run"]:
        for a in visible(fresh(label)):
            for old in getattr(a, "old_env", ()):
                value = "1" if a.nargs == 0 else _sample(a)[0]
                monkeypatch.setenv(old, value)
                got = getattr(fresh(label).parse_args([]), a.dest)
                monkeypatch.delenv(old)
                monkeypatch.setenv(a.env, value)
                want = getattr(fresh(label).parse_args([]), a.dest)
                assert got == want and got != a.default, (label, old, got, want)
                monkeypatch.setenv(old, "0")            # the new name wins when both are set
                assert getattr(fresh(label).parse_args([]), a.dest) == want, (label, a.env, old)
                monkeypatch.delenv(old)
                monkeypatch.delenv(a.env)
                n += 1
    assert n >= 25


def test_deployed_env_files_use_current_names():
    from pathlib import Path
    current = {getattr(a, "env", None) for p in PARSERS.values() for a in visible(p)} | {"EONAV_ZENOH_SHM"}
    for f in (Path(__file__).resolve().parents[1] / "deploy" / "env").glob("*.env"):
        for ln in f.read_text().splitlines():
            var = ln.lstrip("# ").split("=", 1)[0]
            if var.startswith("EONAV_") and "=" in ln:
                assert var in current, f"{f.name}: {var} is not a current flag's variable"


# ---- library settings: the service defaults are the library's ------------------------------------------

def test_obstacle_defaults_are_the_librarys(monkeypatch):
    from eonav.obstacles.detect import ObstacleConfig
    from eonav.services import obstacles
    args = PARSERS["service obstacles"].parse_args([])
    assert obstacles.obstacle_config(args) == ObstacleConfig()
    assert args.max_rel_std == ObstacleConfig().max_rel_std == 0.34     # the dense method's VALID threshold
    a = PARSERS["service obstacles"].parse_args(["--max-rel-std", "0.2", "--ground-down-m", "-3"])
    cfg = obstacles.obstacle_config(a)
    assert cfg.max_rel_std == 0.2 and cfg.ground_down_m == -3.0


def test_pair_policy_defaults_are_the_librarys():
    from eonav.ranging.pair_policy import PairPolicyConfig
    from eonav.services import locator
    assert locator.policy_config(PARSERS["service locator"].parse_args([])) == PairPolicyConfig()
    cfg = locator.policy_config(PARSERS["service locator"].parse_args(["--max-age-s", "0.4", "--max-age", "0.3"]))
    assert cfg.max_age_s == 0.3                        # the last one given wins, whichever spelling
