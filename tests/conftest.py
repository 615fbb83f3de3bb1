"""Test-wide settings: the library's own deprecated spellings are errors in the tests (each
entry point keeps one test of its old spelling, under pytest.warns), so that no test, and no
library code a test runs, uses a spelling that is going away."""


def pytest_configure(config):
    # the options given as keywords (flexmbs.model.options.from_keywords): its message starts
    # with the entry point's call
    config.addinivalue_line(
        "filterwarnings",
        r"error:(optimize_fully|optimize_weakly|multistart)\(.*is deprecated:DeprecationWarning")
