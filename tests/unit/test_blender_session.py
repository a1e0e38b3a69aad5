"""blender.session.import_bpy_into: bpy is imported with TMPDIR pointing at a given folder, which is restored."""

from __future__ import annotations

import os
import sys

from rigidbench.blender.session import import_bpy_into


def test_a_missing_bpy_is_reported_and_tmpdir_restored(tmp_path, monkeypatch):
    monkeypatch.delitem(sys.modules, "bpy", raising=False)  # (restored afterwards if another test imported it)
    seen = []

    class Finder:  # records TMPDIR at the moment bpy is looked up, then refuses it
        def find_spec(self, name, path=None, target=None):
            if name == "bpy":
                seen.append(os.environ.get("TMPDIR"))
                raise ImportError("no bpy here")
            return None

    monkeypatch.setattr(sys, "meta_path", [Finder(), *sys.meta_path])
    monkeypatch.setenv("TMPDIR", "/before")
    assert import_bpy_into(tmp_path) is False
    assert seen == [str(tmp_path)] and os.environ["TMPDIR"] == "/before"
    monkeypatch.delenv("TMPDIR")
    assert import_bpy_into(tmp_path) is False
    assert "TMPDIR" not in os.environ  # unset before, unset after


def test_an_imported_bpy_is_left_alone(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "bpy", object())
    monkeypatch.setenv("TMPDIR", "/before")
    assert import_bpy_into(tmp_path) is True and os.environ["TMPDIR"] == "/before"
