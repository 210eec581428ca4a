from tests.lit.conftest import TINY, synthetic_cache  # noqa: F401
