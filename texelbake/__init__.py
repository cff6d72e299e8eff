"""texelbake: appearance level-of-detail baking (characteristic point maps, BTF LOD, impostors).

The core package is importable without Celery, FastAPI or Redis.
"""

__version__ = "0.1.0"
