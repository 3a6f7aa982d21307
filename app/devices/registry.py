"""Which devices the manager creates, in start order. Each device module offers
``create(manager) -> DeviceHandle | None`` (None when its config says `off`)."""

from __future__ import annotations

import importlib
import importlib.util
import logging
from typing import TYPE_CHECKING

from app.config import AppConfig

if TYPE_CHECKING:
    from app.manager import DeviceFactory

log = logging.getLogger(__name__)

# name → module; the order is the start order (the patient model needs the others' streams).
DEVICE_MODULES: dict[str, str] = {
    "linarm": "app.devices.linarm",
    "physio": "app.devices.physio",
    "fes": "app.devices.rehastim",
    "patient_model": "app.devices.patient_model",
    "vr": "app.devices.vr",
}


def default_factories(config: AppConfig) -> dict[str, DeviceFactory]:
    factories: dict[str, DeviceFactory] = {}
    for name, module_name in DEVICE_MODULES.items():
        if getattr(config.devices, name).mode == "off":
            continue
        if importlib.util.find_spec(module_name) is None:
            log.warning("device %s is not available in this build (%s missing)", name, module_name)
            continue
        module = importlib.import_module(module_name)
        factories[name] = module.create
    return factories
