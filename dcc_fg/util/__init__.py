"""Cross-cutting helpers with no knowledge of cameras or gimbals: version, logging, configuration, errors."""
