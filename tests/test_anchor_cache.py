"""The matched filter's anchor maps are built once per object and anchor settings; per-query settings reuse them."""

from __future__ import annotations

import dataclasses

import pytest

pytest.importorskip("open3d")

from yoto.localize.match import AnchorConfig, MatchConfig, MatchLocalizer, anchor_maps, clear_cache  # noqa: E402
from yoto.localize.ranking import BeliefConfig  # noqa: E402


def test_per_query_settings_reuse_the_anchor_maps_and_anchor_settings_rebuild_them(builtin_models):
    model = builtin_models["fruit"]
    clear_cache()
    coarse = AnchorConfig(anchor_spacing_m=0.004)
    first = anchor_maps(model, coarse)
    query_changed = MatchConfig(anchors=coarse, refine_candidates=5, belief=BeliefConfig(num_candidates=2))
    assert MatchLocalizer(query_changed).prepare_object(model) is first
    assert anchor_maps(model, dataclasses.replace(coarse)) is first  # equal settings, same maps
    finer = anchor_maps(model, dataclasses.replace(coarse, anchor_spacing_m=0.003))
    assert finer is not first and len(finer.points_object) > len(first.points_object)
    clear_cache()


def test_model_cache_builds_once_per_model_and_settings_and_keeps_the_newest(builtin_models):
    from yoto.objects.cache import ModelCache

    builds = []

    def build(model, settings):
        builds.append((model.name, settings))
        return object()

    cache = ModelCache(build, size=2)
    fruit, tool = builtin_models["fruit"], builtin_models["tool"]
    first = cache.get(fruit, 1)
    assert cache.get(fruit, 1) is first and builds == [("fruit", 1)]
    cache.get(fruit, 2)
    cache.get(tool, 1)  # a third entry: the oldest (fruit, 1) goes
    assert cache.get(fruit, 1) is not first and len(builds) == 4
    cache.clear()
    cache.get(tool, 1)
    assert len(builds) == 5
