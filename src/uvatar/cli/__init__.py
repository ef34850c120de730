"""Command-line front end. Each module here registers its commands through :func:`register`.

Commands are thin: parse, call the library, print. Modules import the library lazily inside the
handler so that ``uvatar --help`` stays fast.
"""
