"""Every service flag has an EONAV_* environment default, and no two services read the same variable
for different things (one env file per host must not change two services at once)."""
import argparse
import importlib
import re

SERVICES = ("camera_ingest", "mavlink_ingest", "sync", "locator", "obstacles")
SHARED_ON_PURPOSE = {"EONAV_REPLAY_SHIFT_US"}   # the same shift must reach every replay of one recording


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
