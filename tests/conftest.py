"""Test-wide settings: flexmbs's own DeprecationWarnings are errors.

A library module that still calls a deprecated spelling (the warning attributed to a flexmbs
module), and a test that calls simulate's former keywords, reads Result.settings by key or
gives an optimization's options as keywords, fail; a test checking the old spelling catches its
warning with pytest.warns (which records every warning, these filters aside)."""

_ERRORS = (
    "error::DeprecationWarning:flexmbs",
    r"error:(simulate|simulate_for_adjoint|memory_estimate|simulate_with_error)\(.*\) is "
    r"deprecated:DeprecationWarning",
    r"error:Result\.settings\[.*\] is deprecated:DeprecationWarning",
    # the options given as keywords (flexmbs.model.options.from_keywords): its message starts
    # with the entry point's call
    r"error:(optimize_fully|optimize_weakly|multistart)\(.*is deprecated:DeprecationWarning",
)


def pytest_configure(config):
    for line in _ERRORS:
        config.addinivalue_line("filterwarnings", line)
