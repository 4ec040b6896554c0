"""Statistics over estimates: field reports (``reports``), slip maps (``slipmap``), decimation of
long series for charts and positions (``downsample``) and per-vehicle and server-wide alerts
(``alerts``). Pure computations over estimate arrays and rows; the API and the runtime call them."""
