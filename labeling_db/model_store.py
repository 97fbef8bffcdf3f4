"""Trained models: saved with their arrays and the labels they were trained on, and which one
is active (the app ranks with it, across restarts)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from knotlab.labeling_db.arrays import decode_array, encode_array
from knotlab.labeling_db.bulk import _model_info
from knotlab.labeling_db.errors import (
    RecordNotFoundError,
)
from knotlab.labeling_db.models import (
    DemoLibrary,
    Episode,
    Label,
    ModelActivation,
    ModelArray,
    ModelTrainingLabel,
    TrainedModel,
    utcnow,
)
from knotlab.labeling_db.records import ModelInfo, ModelRecord
from knotlab.labeling_db.rows import _check_json, _check_key, _library_id
from knotlab.labeling_db.store_base import StoreBase

_PG_ACTIVATION_LOCK = 0x6B6E6F76  # serialises "activate if still active" on PostgreSQL


@dataclass(frozen=True)
class ActiveModel:
    """The model the app ranks with (None: nearest neighbour), since when and why."""

    version: str | None
    activated_at: datetime
    reason: str


def _active_row(s: Session) -> tuple[ModelActivation, str | None] | None:
    """The newest activation and its model's version (None: no model was ever activated)."""
    row = s.execute(
        select(ModelActivation, TrainedModel.version)
        .outerjoin(TrainedModel, ModelActivation.model_id == TrainedModel.id)
        .order_by(ModelActivation.id.desc())
        .limit(1)
    ).first()
    return None if row is None else (row[0], row[1])


def _activate(s: Session, url: str, version: str | None, reason: str) -> ActiveModel:
    """Append an activation of ``version`` (in the caller's transaction) unless it is active."""
    current = _active_row(s)
    if current is not None and current[1] == version:
        return ActiveModel(version, current[0].activated_at, current[0].reason)
    model_id = None
    if version is not None:
        model_id = s.scalar(select(TrainedModel.id).where(TrainedModel.version == version))
        if model_id is None:
            raise RecordNotFoundError(f"{url}: no model version {version!r} to activate")
    row = ModelActivation(model_id=model_id, reason=reason, activated_at=utcnow())
    s.add(row)
    s.flush()
    return ActiveModel(version, row.activated_at, reason)


class ModelStore(StoreBase):
    """Trained models: saved with their arrays and the labels they were trained on."""

    # --- trained models

    def save_model(
        self,
        version: str,
        *,
        arrays: Mapping[str, np.ndarray],
        hyperparameters: Mapping[str, Any],
        feature_spec: Mapping[str, Any],
        params: Mapping[str, Any] | None = None,
        metrics: Mapping[str, Any] | None = None,
        library_hash: str | None = None,
        trained_on: Iterable[str] = (),
    ) -> ModelInfo:
        """Store a trained model; `trained_on` lists the execution ids whose labels it used."""
        _check_key("version", version)
        _check_key("library_hash", library_hash, optional=True, limit=128)
        blobs = {}
        for name, arr in arrays.items():
            _check_key("array name", name, limit=100)
            blobs[name] = encode_array(arr, "float64", name=f"model array {name!r}")
        docs = {
            "hyperparameters": dict(hyperparameters),
            "feature_spec": dict(feature_spec),
            "params": dict(params or {}),
            "metrics": dict(metrics or {}),
        }
        for what, doc in docs.items():
            _check_json(what, doc)
        execution_ids = list(dict.fromkeys(trained_on))

        def work(s: Session) -> ModelInfo:
            model = TrainedModel(version=version, library_id=_library_id(s, library_hash), **docs)
            s.add(model)
            with self._conflicts(f"model version {version!r} already exists"):
                s.flush()
            s.add_all(ModelArray(model_id=model.id, name=k, data=v) for k, v in blobs.items())
            label_ids: list[int] = []
            for j in range(0, len(execution_ids), 500):
                chunk = execution_ids[j : j + 500]
                found: dict[Any, Any] = dict(
                    s.execute(
                        select(Episode.execution_key, Episode.id).where(
                            Episode.execution_key.in_(chunk)
                        )
                    ).all()
                )
                missing = [k for k in chunk if k not in found]
                if missing:
                    raise RecordNotFoundError(
                        f"{self.url}: model {version!r} names unknown execution ids {missing[:5]}"
                    )
                label_ids += s.scalars(select(Label.id).where(Label.episode_id.in_(found.values())))
            s.add_all(ModelTrainingLabel(model_id=model.id, label_id=i) for i in label_ids)
            s.flush()
            return _model_info(model, library_hash, len(label_ids))

        return self._run(work, write=True)

    def list_models(self) -> list[ModelInfo]:
        """Every stored model version, oldest first (without arrays)."""

        def work(s: Session) -> list[ModelInfo]:
            counts: dict[Any, Any] = dict(
                s.execute(
                    select(ModelTrainingLabel.model_id, func.count()).group_by(
                        ModelTrainingLabel.model_id
                    )
                ).all()
            )
            rows = s.execute(
                select(TrainedModel, DemoLibrary.library_hash)
                .outerjoin(DemoLibrary, TrainedModel.library_id == DemoLibrary.id)
                .order_by(TrainedModel.id)
            )
            return [_model_info(m, h, counts.get(m.id, 0)) for m, h in rows]

        return self._run(work, write=False)

    def load_model(self, version: str | None = None) -> ModelRecord:
        """A model with its arrays: `version`, or the newest one when None."""

        def work(s: Session) -> ModelRecord:
            q = select(TrainedModel, DemoLibrary.library_hash).outerjoin(
                DemoLibrary, TrainedModel.library_id == DemoLibrary.id
            )
            q = (
                q.order_by(TrainedModel.id.desc())
                if version is None
                else q.where(TrainedModel.version == version)
            )
            row = s.execute(q.limit(1)).first()
            if row is None:
                what = "no models stored" if version is None else f"no model version {version!r}"
                raise RecordNotFoundError(f"{self.url}: {what}")
            model, lib = row
            n = s.scalar(
                select(func.count())
                .select_from(ModelTrainingLabel)
                .where(ModelTrainingLabel.model_id == model.id)
            )
            arrays = {
                a.name: decode_array(a.data, where=f"model {model.version!r} array {a.name!r}")
                for a in s.scalars(select(ModelArray).where(ModelArray.model_id == model.id))
            }
            return ModelRecord(_model_info(model, lib, int(n or 0)), arrays)

        return self._run(work, write=False)

    # --- the active model

    def active_model(self) -> ActiveModel | None:
        """The model activated last (None: none ever was, e.g. a new store)."""

        def work(s: Session) -> ActiveModel | None:
            found = _active_row(s)
            if found is None:
                return None
            row, version = found
            return ActiveModel(version, row.activated_at, row.reason)

        return self._run(work, write=False)

    def set_active_model(self, version: str | None, *, reason: str) -> ActiveModel:
        """Make stored model ``version`` (None: nearest neighbour) the active one; a no-op when
        it already is. Only stored models can be active, so a restart can always load it."""
        _check_key("version", version, optional=True)
        _check_key("reason", reason)
        return self._run(lambda s: _activate(s, self.url, version, reason), write=True)

    def activate_if_active(self, version: str, *, expected: str | None, reason: str) -> bool:
        """Activate ``version`` only while ``expected`` is still the active model (None: no
        model or nearest neighbour); False, and nothing changed, when someone switched since."""
        _check_key("version", version)
        _check_key("expected", expected, optional=True)
        _check_key("reason", reason)

        def work(s: Session) -> bool:
            if self.dialect == "postgresql":  # SQLite writers are serialised by BEGIN IMMEDIATE
                s.execute(select(func.pg_advisory_xact_lock(_PG_ACTIVATION_LOCK)))
            current = _active_row(s)
            if (None if current is None else current[1]) != expected:
                return False
            _activate(s, self.url, version, reason)
            return True

        return self._run(work, write=True)

    def model_training_executions(self, version: str) -> list[str]:
        """Execution ids whose labels trained model `version`."""

        def work(s: Session) -> list[str]:
            mid = s.scalar(select(TrainedModel.id).where(TrainedModel.version == version))
            if mid is None:
                raise RecordNotFoundError(f"{self.url}: no model version {version!r}")
            q = (
                select(Episode.execution_key)
                .join(Label, Label.episode_id == Episode.id)
                .join(ModelTrainingLabel, ModelTrainingLabel.label_id == Label.id)
                .where(ModelTrainingLabel.model_id == mid)
                .group_by(Episode.id, Episode.execution_key)
                .order_by(Episode.id)
            )
            return list(s.scalars(q))

        return self._run(work, write=False)
