"""Ground-station star pattern identification for TUBSAT-class star field sensors.

Stages, each a module or subpackage, data flowing one way:
telemetry -> extraction -> identification -> attitude -> storage/api -> console.
"""

__version__ = "0.1.0"
