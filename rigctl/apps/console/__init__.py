"""The operator console of `rigctl daemon --console` (docs/console.md)."""
