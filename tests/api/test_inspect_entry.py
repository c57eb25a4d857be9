"""The service's handover to the pipeline: a function the settings hold, pipeline.run.inspect by default."""

from __future__ import annotations

import pipeline.run
from app.settings import ENV_PREFIX, Settings

ENTRY_VARIABLE = f"{ENV_PREFIX}INSPECT_ENTRY"


def test_the_default_entry_is_the_pipelines_inspect(tmp_path, monkeypatch):
    monkeypatch.delenv(ENTRY_VARIABLE, raising=False)
    settings = Settings(data_dir=tmp_path)
    assert settings.inspect_entry is pipeline.run.inspect
    assert settings.to_env()[ENTRY_VARIABLE] == "pipeline.run:inspect"


def test_the_fixture_swaps_in_the_test_double_and_names_it_for_the_consumer(settings):
    entry = settings.inspect_entry
    assert callable(entry)
    assert entry.__module__ == "tests.api.fake_pipeline"
    named = settings.to_env()[ENTRY_VARIABLE]
    assert named == "tests.api.fake_pipeline:inspect"
    assert Settings(data_dir=settings.data_dir, inspect_entry=named).inspect_entry is entry


def test_a_function_is_held_as_given(tmp_path):
    def stand_in(*args, **kwargs):
        raise AssertionError("not called")

    assert Settings(data_dir=tmp_path, inspect_entry=stand_in).inspect_entry is stand_in
